"""racklay calibrate --weights W --data ROOT --split val --out calibrated.safetensors"""
from __future__ import annotations

from racklay.commands import add_progress_arg, show_progress
from racklay.config import at_least


def register(sub) -> None:
    from racklay.predict import add_precision_args
    from racklay.release import add_weights_arg

    p = sub.add_parser(
        "calibrate", help="fit the model's decision biases on a validation split",
        description="Pick, per view, additive biases on the shelf and box logits (background fixed at 0) "
                    "that maximise the mean of the dataset-level shelf and box IoU on a split the model "
                    "was not trained on, and write a copy of the checkpoint that carries them: `predict`, "
                    "`eval`, `analyze` and the annotator then use them. A model trained on layouts that are "
                    "~99% background under-calls boxes with a plain argmax; this is the layout analogue of "
                    "choosing a detector's score threshold. Probabilities (and AP) are unchanged. "
                    "Fit on a validation split, never on the test split you report.",
        epilog="example: racklay calibrate --weights runs/x/best.safetensors --data datasets/release "
               "--split val --limit 500 --out runs/x/calibrated.safetensors")
    add_weights_arg(p, what="model checkpoint (.safetensors) to calibrate")
    p.add_argument("--data", required=True, help="RackLay-format dataset folder")
    p.add_argument("--split", default="val", help="split to fit on (default: val)")
    p.add_argument("--limit", type=at_least(1), default=None, help="use only the first N images of the split")
    p.add_argument("--batch-size", type=at_least(1), default=8, help="images per forward pass (default 8)")
    add_precision_args(p)
    p.add_argument("--threads", type=at_least(1), default=None, help="intra-op threads (default: library default)")
    p.add_argument("--out", required=True, help="calibrated checkpoint to write (.safetensors)")
    p.add_argument("--json", default=None, help="also write the fitted biases and scores as JSON here")
    add_progress_arg(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from dataclasses import asdict
    from pathlib import Path

    from racklay.atomic import atomic_write_json
    from racklay.calibrate import fit_decision_bias, format_fits, write_calibrated
    from racklay.commands import CLIError, check_out_file
    from racklay.predict import Predictor
    from racklay.release import weights_for_cli

    weights = weights_for_cli(args.weights)
    if Path(weights).suffix.lower() == ".onnx":
        raise CLIError(f"{weights}: calibrate a .safetensors checkpoint, then export it")
    if Path(args.out).suffix.lower() != ".safetensors":
        raise CLIError(f"{args.out}: --out must be a .safetensors file")
    if Path(args.out).resolve() == Path(weights).resolve():
        raise CLIError(f"{args.out}: --out must differ from --weights (the input stays as it is)")
    check_out_file(args.out, "calibrated checkpoint")
    check_out_file(args.json, "--json file")
    pred = Predictor(weights, threads=args.threads, precision=args.precision)
    fits = fit_decision_bias(pred, args.data, split=args.split, batch_size=args.batch_size, limit=args.limit,
                             progress=show_progress(args))
    print(f"{Path(weights).name} on {args.data} [{args.split}]: dataset-level IoU at "
          f"{pred.layout_size}x{pred.layout_size}, plain decision → calibrated")
    print(format_fits(fits))
    out = write_calibrated(weights, args.out, fits, args.data, args.split)
    print(f"calibrated checkpoint written to {out}")
    if args.json:
        atomic_write_json(args.json, {"weights": weights, "data": str(args.data), "split": args.split,
                                      "views": [asdict(f) for f in fits]})
        print(f"fit written to {args.json}")
    return 0
