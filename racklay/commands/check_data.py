"""racklay check-data ROOT"""
from __future__ import annotations

from racklay.commands import add_progress_arg, show_progress
from racklay.config import at_least


def register(sub) -> None:
    p = sub.add_parser(
        "check-data", help="validate a RackLay-format dataset",
        description="Validate every sample of a RackLay-format dataset: readable images, layout "
                    "shapes, dtype and values (0/115/255 only), image/layout pairs, split entries "
                    "pointing at missing files and duplicate entries. Prints a summary and one line "
                    "per problem naming the file; exits 0 only when the dataset is clean.")
    p.add_argument("root", help="dataset folder (Images/, topLayouts/, frontLayouts/, splits/)")
    p.add_argument("--R", type=at_least(1), default=None, help="expected number of shelf channels")
    p.add_argument("--D", type=at_least(1), default=None, help="expected layout size in pixels")
    p.add_argument("--workers", type=at_least(1), default=1,
                   help="check in this many processes (the same report; default 1)")
    p.add_argument("--json", default=None, help="also write the report as JSON here")
    p.add_argument("--max-problems", type=at_least(1), default=200, help="print at most this many problem lines (all are counted)")
    add_progress_arg(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from racklay.atomic import atomic_write_json
    from racklay.commands import check_out_file
    from racklay.data import check_dataset

    check_out_file(args.json, "--json file")
    rep = check_dataset(args.root, R=args.R, D=args.D, progress=show_progress(args), workers=args.workers)
    for line in rep.problems[: args.max_problems]:
        print(line)
    if len(rep.problems) > args.max_problems:
        print(f"... and {len(rep.problems) - args.max_problems} more problem(s)")
    print(rep.summary())
    if args.json:
        atomic_write_json(args.json, {"root": str(rep.root), "samples": rep.samples, "views": list(rep.views),
                                      "R": rep.R, "D": rep.D, "splits": rep.splits, "problems": rep.problems,
                                      "ok": rep.ok})
    return 0 if rep.ok else 1
