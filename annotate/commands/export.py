"""annotate export PROJECT_DIR --out DATASET_ROOT"""
from __future__ import annotations

import sys


def register(sub) -> None:
    from annotate.dataset import parse_statuses
    from annotate.store import DONE_STATUSES
    from racklay.config import at_least

    p = sub.add_parser(
        "export", help="write the annotations as a RackLay-format dataset",
        description="Compute every finished annotation's per-shelf top and front layouts and write a "
                    "RackLay-format dataset (Images/, topLayouts/, frontLayouts/, meta/, splits/) that "
                    "`racklay check-data` accepts and training / `transfer finetune` read. Samples are "
                    "numbered 000000... in file-name order; meta/NNNNNN.json names the source photo. "
                    "Every annotation and photo is checked before anything is written (an annotation "
                    "must fit its photo: same name and size, every point inside it, no box without "
                    "area); the first bad one stops the export unless --skip-invalid is given. The "
                    "geometry's warnings (also in meta/NNNNNN.json) are printed. The dataset is "
                    "built in a hidden folder beside --out and renamed to --out at the end, so a failed "
                    "export leaves nothing behind.")
    p.add_argument("project", help="project folder")
    p.add_argument("--out", required=True, help="dataset folder to create (must be new or empty)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--split", default=None, help="exact split sizes, e.g. train=442,test=100")
    g.add_argument("--split-fractions", default=None,
                   help="split fractions summing to 1, e.g. train=0.8,test=0.2 (the default)")
    g.add_argument("--split-file", default=None, metavar="TSV",
                   help="the split of every photo from a tab-separated file with 'file' and 'split' "
                        "columns (e.g. the project's SOURCES.tsv, split by site so that no site is in "
                        "two splits); every exported photo must be listed")
    p.add_argument("--seed", type=at_least(0), default=0, help="seed of the split shuffle (default 0)")
    p.add_argument("--only-status", type=parse_statuses, default=DONE_STATUSES,
                   help=f"export images with these statuses (default {','.join(DONE_STATUSES)})")
    p.add_argument("--skip-invalid", action="store_true",
                   help="leave out (and list) annotations that do not fit their photo or give no layouts, "
                        "instead of stopping at the first")
    p.set_defaults(func=run)


def run(args) -> int:
    from annotate.dataset import export_project, parse_counts, read_split_file
    from annotate.store import Project

    counts = parse_counts(args.split, "--split") if args.split else None
    fractions = parse_counts(args.split_fractions, "--split-fractions") if args.split_fractions else None
    split_of = read_split_file(args.split_file) if args.split_file else None
    project = Project(args.project, create=False)
    res = export_project(project, args.out, counts=counts, fractions=fractions, seed=args.seed,
                         only_status=args.only_status, progress=sys.stderr.isatty(), skip_invalid=args.skip_invalid,
                         split_of=split_of)
    for path, why in res["skipped"]:
        print(f"annotate export: skipped: {why}", file=sys.stderr)
    for w in res["warnings"]:
        print(f"annotate export: warning: {w}", file=sys.stderr)
    sp = ", ".join(f"{k}={v}" for k, v in res["splits"].items())
    print(f"exported {res['images']} image(s) to {res['out']} (splits: {sp})")
    if res["skipped"]:
        print(f"skipped {len(res['skipped'])} invalid annotation(s) (listed above)")
    lo = res["left_out"]
    parts = [f"{n} with status {st}" for st, n in sorted(lo["other_status"].items())]
    if lo["unannotated"]:
        parts.append(f"{lo['unannotated']} photo(s) not annotated")
    if lo["no_photo"]:
        parts.append(f"{len(lo['no_photo'])} annotation file(s) whose photo is no longer in the project "
                     f"(first: {lo['no_photo'][0]})")
    if parts:
        print("left out: " + "; ".join(parts))
    return 0
