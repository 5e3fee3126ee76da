"""racklay score --pred PRED_ROOT --gt GT_ROOT"""
from __future__ import annotations

import os


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


def score_roots(pred_root, gt_root, split=None):
    """Metrics dict for predicted layouts in pred_root against gt_root."""
    from racklay.cli import CLIError
    from racklay.data import RackLayRoot
    from racklay.metrics import LayoutMetrics

    for root, what in ((pred_root, "predictions"), (gt_root, "ground-truth dataset")):
        if not os.path.isdir(root):
            raise CLIError(f"{root}: {what} folder not found")
    pred, gt = RackLayRoot(pred_root), RackLayRoot(gt_root)
    views = [v for v in pred.views() if v in gt.views()]
    if not views:
        raise CLIError(f"no common view: {pred.root} has {list(pred.views()) or 'no layouts'}, "
                       f"{gt.root} has {list(gt.views()) or 'no layouts'}")
    predicted = {view: set(pred.layout_ids(view)) for view in views}
    if split:
        ids = sorted(gt.resolve(split))
        if not ids:
            raise CLIError(f"{gt.root}: split {split!r} is empty")
    else:
        ids = sorted(set().union(*predicted.values()))
        if not ids:
            raise CLIError(f"{pred.root}: no predicted layouts to score")
    # every image to score needs a prediction in every view scored: a missing file is an error,
    # never a silently smaller denominator
    for view in views:
        missing = [i for i in ids if i not in predicted[view]]
        if missing:
            first = pred.layout_path(view, missing[0])
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise CLIError(f"{first}: prediction missing{more}; "
                           f"{len(ids)} image(s) to score in view {view}")
    # the shape most ground-truth files have: a file that differs is the one named, whether it is a
    # ground-truth file or a prediction
    ref = gt.layout_shape(ids, views)
    R, D = ref if ref else (None, None)
    m = LayoutMetrics()
    for view in views:
        for sid in ids:
            gpath = gt.layout_path(view, sid)
            if not gpath.exists():
                raise CLIError(f"{gpath}: ground truth missing for predicted {view} layout {sid}")
            g = gt.read_layouts(view, sid, R=R, D=D)
            p = pred.read_layouts(view, sid, R=g.shape[0], D=g.shape[1])
            m.update(view, p, g)
    n = len(ids)
    return m.result(), n


def run(args) -> int:
    from racklay.atomic import atomic_write_json
    from racklay.metrics import format_tables

    result, n = score_roots(args.pred, args.gt, args.split)
    print(format_tables(result, title=f"{n} images: {args.pred} vs {args.gt}"))
    if args.json:
        atomic_write_json(args.json, result)
        print(f"metrics written to {args.json}")
    return 0
