"""racklay score --pred PRED_ROOT --gt GT_ROOT"""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "score", help="score predicted layouts against ground truth",
        description="Score a folder of predicted layouts (RackLay format: topLayouts/topNNNNNN.npy, "
                    "frontLayouts/frontNNNNNN.npy) against a ground-truth dataset. Prints the paper's "
                    "Table-1 layout (paper protocol; the paper's 'mAP' is pixel precision) and "
                    "dataset-level IoU / precision / recall from the accumulated confusion matrix.")
    p.add_argument("--pred", required=True, help="folder with predicted topLayouts/ and/or frontLayouts/")
    p.add_argument("--gt", required=True, help="ground-truth RackLay-format dataset")
    p.add_argument("--split", default=None, help="score exactly the ids of this ground-truth split; every one needs a prediction (default: every predicted id)")
    p.add_argument("--json", default=None, help="write the metrics as JSON here")
    p.set_defaults(func=run)


def run(args) -> int:
    from racklay.atomic import atomic_write_json
    from racklay.commands import check_out_file
    from racklay.evaluate import score_folders
    from racklay.metrics import format_tables

    check_out_file(args.json, "--json file")
    result, n = score_folders(args.pred, args.gt, args.split)
    print(format_tables(result, title=f"{n} images: {args.pred} vs {args.gt}"))
    if args.json:
        atomic_write_json(args.json, result)
        print(f"metrics written to {args.json}")
    return 0
