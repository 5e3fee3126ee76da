"""racklay predict IMAGES_OR_FOLDER... --weights W --out DIR"""
from __future__ import annotations

import sys

from racklay.commands import add_progress_arg, show_progress
from racklay.config import at_least, positive_float


def register(sub) -> None:
    from racklay.predict import add_flip_average_arg, add_precision_args, add_rack_box_arg, add_shelf_length_arg
    from racklay.release import add_weights_arg

    p = sub.add_parser(
        "predict", help="predict per-shelf layouts for photos",
        description="Predict every shelf's top- and front-view layout for each photo (files, or every "
                    "file in a folder; any image size, resized to the model's input). OUT becomes a "
                    "RackLay-format dataset: Images/ID.png, topLayouts/topID.npy, "
                    "frontLayouts/frontID.npy (0/115/255), meta/ID.json, so `racklay score --pred OUT` "
                    "and `racklay show OUT` read it; plus colour PNGs per shelf (png/ID_VIEW_shelfK.png) "
                    "and a paper-style figure per photo (figures/ID.png). ID is the file stem. A file "
                    "that is not a readable image gets a one-line error and the rest still run; the exit "
                    "code is 1 if any input failed.")
    p.add_argument("inputs", nargs="+", metavar="IMAGES_OR_FOLDER", help="image files and/or folders")
    add_weights_arg(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--backend", choices=("torch", "onnx"), default="torch",
                   help="torch (default) or onnxruntime (a checkpoint is exported in memory)")
    p.add_argument("--layout-size", type=at_least(2), default=None, metavar="D",
                   help="write layouts at D x D over the same metric extent, e.g. 512 to score against the "
                        "original RackLay data: a struct model draws its rectangles at D, any other model's "
                        "output is resized (nearest) (default: the model's size)")
    add_shelf_length_arg(p)
    p.add_argument("--load-width", type=positive_float, default=None, metavar="M",
                   help="the loads' width in metres along the shelf when all are alike (pallets stand 0.8, 1.0 "
                        "or 1.2 m wide): the figures outline each box run cut into loads of that width "
                        "(as `racklay analyze --load-width`; the layouts are unchanged)")
    add_rack_box_arg(p)
    add_precision_args(p)
    add_flip_average_arg(p)
    p.add_argument("--threads", type=at_least(1), default=None, help="intra-op threads (default: library default)")
    p.add_argument("--no-figure", action="store_true", help="skip the paper-style figures")
    p.add_argument("--no-png", action="store_true", help="skip the per-shelf colour PNGs")
    p.add_argument("--full", action="store_true", help="figures show the whole grid, not a crop")
    add_progress_arg(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from racklay.commands import CLIError, check_out_folder
    from racklay.data import check_prediction_out
    from racklay.predict import Predictor, list_inputs, predict_folder
    from racklay.release import weights_for_cli

    args.weights = weights_for_cli(args.weights)

    out = Path(args.out).resolve()
    files = list_inputs(args.inputs)
    if not files:
        sets = [p for p in map(Path, args.inputs) if (p / "Images").is_dir()]
        hint = f"; a RackLay dataset? its photos are in {sets[0] / 'Images'}" if sets else " (empty folder?)"
        raise CLIError(f"{' '.join(map(str, args.inputs))}: no photos to predict{hint}")
    check_out_folder(args.out)
    check_prediction_out(args.out)
    for f in files:
        if f.resolve().parent == out / "Images":
            raise CLIError(f"{f}: input lies in the output's Images/ folder; choose another --out "
                           "(predictions would overwrite that dataset)")
    if args.layout_size is not None and args.layout_size < 1:
        raise CLIError(f"--layout-size must be >= 1, got {args.layout_size}")
    pred = Predictor(args.weights, backend=args.backend, threads=args.threads,
                     precision=args.precision, flip_average=args.flip_average)
    rep = predict_folder(pred, args.inputs, args.out, figure=not args.no_figure, png=not args.no_png,
                         crop=not args.full, layout_size=args.layout_size, shelf_length=args.shelf_length,
                         rack_box=args.rack_box, load_width=args.load_width,
                         progress=show_progress(args))
    D = args.layout_size or pred.layout_size
    scale = f", shelves scaled to {args.shelf_length:g} m" if args.shelf_length else ""
    scale += ", flip-averaged" if args.flip_average else ""
    scale += ", read in the rack box" if args.rack_box else ""
    print(f"{rep.summary()} -> {args.out} (backend {pred.backend}, "
          f"{pred.image_size[1]}x{pred.image_size[0]} input, {D}x{D} layouts{scale})")
    if rep.scale_note():
        print(rep.scale_note(), file=sys.stderr)
    return 0 if rep.ok else 1
