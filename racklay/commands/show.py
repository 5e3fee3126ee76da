"""racklay show ROOT --index N --out fig.png"""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "show", help="draw an image beside every shelf's top and front layout",
        description="Draw a paper-style figure: the image beside every shelf's top-view (upper row) "
                    "and front-view (lower row) layout, colour-coded (background / shelf / box) with a "
                    "legend. Layouts are cropped to their content unless --full is given.")
    p.add_argument("root", help="RackLay-format dataset folder")
    sel = p.add_mutually_exclusive_group()
    sel.add_argument("--index", type=int, default=0, help="position of the sample in sorted ids (or in --split)")
    sel.add_argument("--id", default=None, help="sample id, e.g. 000042")
    p.add_argument("--split", default=None, help="index into this split instead of all images")
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--full", action="store_true", help="show the whole D x D grid, not a crop")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from racklay.commands import CLIError
    from racklay.data import RackLayRoot
    from racklay.viz import layout_figure

    ds = RackLayRoot(args.root).require()
    ext = Path(args.out).suffix.lower()
    if ext not in (".png", ".jpg", ".jpeg", ".pdf", ".svg"):
        raise CLIError(f"{args.out}: unsupported figure format {ext or '(none)'!r}; use .png, .jpg, .pdf or .svg")
    ids = ds.resolve(args.split)
    if args.id is not None:
        sid = args.id
    else:
        if not ids:
            where = f"split {args.split!r} of {ds.root} is empty" if args.split not in (None, "all") \
                else f"{ds.root}: no images in {ds.root / 'Images'}"
            raise CLIError(where)
        if not 0 <= args.index < len(ids):
            raise CLIError(f"--index {args.index} out of range: {ds.root}" + (f" [{args.split}]" if args.split else "")
                           + f" has {len(ids)} samples")
        sid = ids[args.index]
    views = ds.views()
    # the shape most of the dataset's layouts have: a file that differs is the one named
    R, D = ds.layout_shape([sid, *ids[:24]]) or (None, None)
    top = ds.read_layouts("top", sid, R=R, D=D) if "top" in views else None
    front = ds.read_layouts("front", sid, R=R, D=D) if "front" in views else None
    if top is not None and front is not None and top.shape != front.shape:
        raise CLIError(f"{ds.layout_path('front', sid)}: shape {front.shape} differs from its top "
                       f"layout's {top.shape} ({ds.layout_path('top', sid)})")
    layout_figure(ds.read_image(sid), top, front, out=args.out, title=f"{ds.root.name} / {sid}",
                  crop=not args.full)
    print(f"figure written to {args.out}")
    return 0
