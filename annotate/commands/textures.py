"""annotate textures PROJECT_DIR --out FOLDER"""
from __future__ import annotations

import sys


def register(sub) -> None:
    from annotate.dataset import parse_statuses
    from annotate.store import DONE_STATUSES
    from annotate.textures import TEXTURE_PX, TILE_M, TILE_RANGE_M

    p = sub.add_parser(
        "textures", help="write the labelled boxes' faces as WareSynth carton textures",
        description="Cut the front face of every labelled box of the finished photos out of its photo, "
                    "rectified through the rack plane, in tiles of about --tile metres (one carton's face), "
                    f"each brought to one median brightness and written as a {TEXTURE_PX}x{TEXTURE_PX} JPEG. "
                    "`racklay synth --set texture_dir=FOLDER` then draws cartons with them, so renders look "
                    "more like your site (docs/waresynth.md). "
                    "Take them from the photos you train on (--split-file SOURCES.tsv --split train), never "
                    "from the photos you test on. The folder is built beside --out and renamed into place.")
    p.add_argument("project", help="project folder")
    p.add_argument("--out", required=True, help="folder to create (must be new or empty)")
    p.add_argument("--split-file", default=None, metavar="TSV",
                   help="tab-separated file with 'file' and 'split' columns (e.g. the project's SOURCES.tsv)")
    p.add_argument("--split", default=None, help="only the photos of this split of --split-file (e.g. train)")
    p.add_argument("--tile", type=float, default=TILE_M,
                   help=f"tile side on the rack plane, metres, {TILE_RANGE_M[0]} to {TILE_RANGE_M[1]} "
                        f"(default {TILE_M}: about one carton)")
    p.add_argument("--only-status", type=parse_statuses, default=DONE_STATUSES,
                   help=f"use photos with these statuses (default {','.join(DONE_STATUSES)})")
    p.set_defaults(func=run)


def run(args) -> int:
    from annotate.dataset import read_split_file
    from annotate.store import Project
    from annotate.textures import export_textures

    split_of = read_split_file(args.split_file) if args.split_file else None
    res = export_textures(Project(args.project, create=False), args.out, split_of=split_of, split=args.split,
                          only_status=args.only_status, tile=args.tile, progress=sys.stderr.isatty())
    left = "; ".join(f"{v} {k}" for k, v in res["left_out"].items() if v)
    print(f"wrote {res['textures']} texture(s) from {res['photos']} photo(s) to {res['out']}"
          + (f" (left out: {left})" if left else ""))
    print(f"use them: racklay synth --recipe mixed --set texture_dir={res['out']} ...")
    return 0
