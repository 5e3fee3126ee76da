"""racklay eval --weights W --data ROOT --split test [--json out.json]"""
from __future__ import annotations

from racklay.commands import add_progress_arg, show_progress
from racklay.config import at_least, positive_float


def register(sub) -> None:
    from racklay.predict import add_flip_average_arg, add_precision_args
    from racklay.release import add_weights_arg

    p = sub.add_parser(
        "eval", help="evaluate a trained model on a dataset split",
        description="Run a trained model (checkpoint from `racklay train`, or an ONNX file from "
                    "`racklay export`) on a split of a RackLay-format dataset and print the paper's "
                    "Table-1 layout (paper protocol: per image x shelf, a shelf empty in both "
                    "prediction and truth counts as 1; the paper's 'mAP' is pixel precision) and the "
                    "dataset-level IoU / precision / recall / AP (confusion matrix and score histograms "
                    "over every pixel; judge progress by these). Layouts are compared at the model's "
                    "layout size unless --native is given.")
    add_weights_arg(p)
    p.add_argument("--data", required=True, help="RackLay-format dataset folder")
    p.add_argument("--split", default="test", help="split to evaluate (splits/NAME.txt), or 'all' (default: test)")
    p.add_argument("--batch-size", type=at_least(1), default=8, help="images per forward pass (default 8)")
    p.add_argument("--backend", choices=("torch", "onnx"), default="torch",
                   help="run the model with torch (default) or onnxruntime")
    p.add_argument("--limit", type=at_least(1), default=None, help="evaluate only the first N images of the split")
    p.add_argument("--native", action="store_true",
                   help="score at the dataset's own layout resolution: a struct model draws its layouts "
                        "there, any other model's are upsampled (nearest)")
    scale = p.add_mutually_exclusive_group()
    scale.add_argument("--scale-from-truth", action="store_true",
                       help="scale every predicted shelf to its true shelf's length before scoring: the "
                            "score of the shape alone, which a known dimension (--shelf-length) would give")
    scale.add_argument("--shelf-length", type=positive_float, default=None, metavar="M",
                       help="scale every predicted shelf to this known length in metres before scoring")
    p.add_argument("--no-gap-cut", action="store_true",
                   help="a struct model with a gap output: draw boxes from the box output alone, without "
                        "the gap output's cuts (what the cuts add or cost on this data; torch backend)")
    p.add_argument("--workers", type=at_least(0), default=0, help="DataLoader worker processes (default 0)")
    add_precision_args(p)
    add_flip_average_arg(p)
    p.add_argument("--threads", type=at_least(1), default=None, help="intra-op threads (default: library default)")
    p.add_argument("--save-predictions", default=None, metavar="DIR",
                   help="also write the predicted layouts as a RackLay dataset in DIR, at the dataset's "
                        "layout size (`racklay score --pred DIR --gt DATA` scores them)")
    p.add_argument("--json", default=None, help="write the run description and metrics as JSON here")
    add_progress_arg(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from racklay.atomic import atomic_write_json
    from racklay.commands import check_out_file, check_out_folder
    from racklay.evaluate import eval_report, evaluate
    from racklay.metrics import format_tables
    from racklay.predict import Predictor
    from racklay.release import weights_for_cli

    args.weights = weights_for_cli(args.weights)
    check_out_file(args.json, "--json file")
    if args.save_predictions:
        check_out_folder(args.save_predictions, "--save-predictions folder")
        from racklay.data import check_prediction_out
        check_prediction_out(args.save_predictions, data=args.data)
    pred = Predictor(args.weights, backend=args.backend, threads=args.threads,
                     precision=args.precision, cut_gaps=not args.no_gap_cut,
                     flip_average=args.flip_average)
    result = evaluate(pred, args.data, split=args.split, batch_size=args.batch_size, workers=args.workers,
                      progress=show_progress(args),
                      limit=args.limit, native=args.native, pred_out=args.save_predictions,
                      shelf_length=args.shelf_length, scale_from_truth=args.scale_from_truth)
    scale = ("from truth" if args.scale_from_truth else
             f"shelf length {args.shelf_length:g} m" if args.shelf_length else "model")
    report = eval_report(result, args.weights, args.data, args.split, cfg=pred.cfg, native=args.native,
                         scale=scale, gap_cut=not args.no_gap_cut, flip_average=args.flip_average)
    where = "dataset resolution" if args.native else f"{pred.layout_size}x{pred.layout_size}"
    print(format_tables(result, title=f"{Path(args.weights).name} on {args.data} [{args.split}], "
                                      f"{report['images']} images, layouts at {where}"
                                      + ("" if scale == "model" else f", scale {scale}")
                                      + (", gap cut off" if args.no_gap_cut else "")
                                      + (", flip-averaged" if args.flip_average else "")))
    if args.save_predictions:
        print(f"predicted layouts written to {args.save_predictions}")
    if args.json:
        atomic_write_json(args.json, report)
        print(f"metrics written to {args.json}")
    return 0
