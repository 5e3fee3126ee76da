"""Evaluate a trained model on a RackLay-format split: the paper's Table-1 numbers (paper
protocol) and dataset-level IoU / precision / recall / AP, via `racklay.metrics.LayoutMetrics`.

By default layouts are compared at the model's layout size S (ground truth resized with
`racklay.layout.resize_layouts`, as in training). `native=True` instead scores at the dataset's
own resolution D, which is what the paper's numbers at D = 512 mean when the model was trained at
a smaller S: a struct model on the torch backend draws its layouts at D (`Predictor.draw_at`),
any other model's are upsampled (nearest, at pixel centres).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from . import layout as L


def _predictor(weights, backend: str, threads: int | None):
    from .predict import Predictor

    if isinstance(weights, Predictor):
        return weights
    if isinstance(weights, tuple) and len(weights) == 2:  # (model, cfg) in memory
        return Predictor.from_model(*weights)
    return Predictor(weights, backend=backend, threads=threads)


def split_dataset(pred, data, split: str | None, limit: int | None = None, spans: bool = False):
    """The (root, views, RackLayDataset) a model is scored on: `split` of the dataset at `data`
    (its first `limit` ids), the model's views that the dataset has, at the model's input and
    layout sizes (with `spans`, each item's level spans on the model's input too). One-line errors
    name the folder, or the weights when the model's R does not fit."""
    from .data import RackLayRoot
    from .torchdata import RackLayDataset

    root = RackLayRoot(data).require()
    ids = root.resolve(split)
    if limit is not None:
        ids = ids[: int(limit)]
    if not ids:
        raise ValueError(f"{root.root}: split {split!r} has no samples")
    views = [v for v in pred.views if v in root.views()]
    if not views:
        raise ValueError(f"{root.root}: no layouts for the model's views {'/'.join(pred.views)} "
                         f"(dataset has {'/'.join(root.views()) or 'none'})")
    ref = root.layout_shape(ids, views)
    if ref is not None and ref[0] != pred.R:
        # the model does not fit the data: name the model, not the first dataset file read
        model = pred.weights or "the model"
        raise ValueError(f"{model}: the model predicts R={pred.R} shelves but the layouts in {root.root} "
                         f"have R={ref[0]}; use a model trained for R={ref[0]}")
    ds = RackLayDataset(root.root, ids=ids, image_size=pred.image_size, layout_size=pred.layout_size, views=views,
                        R=pred.R, letterbox=pred.cfg.letterbox, spans=spans)
    return root, views, ds


def evaluate(weights, data, split: str | None = "test", batch_size: int = 8, backend: str = "torch",
             workers: int = 0, progress: bool = True, limit: int | None = None, native: bool = False,
             with_probs: bool = True, threads: int | None = None, pred_out: str | os.PathLike | None = None,
             shelf_length: float | None = None, scale_from_truth: bool = False) -> dict:
    """Score `weights` (checkpoint path, ONNX path, a `Predictor`, or `(model, cfg)`) on the
    `split` of the dataset at `data`. Returns the `LayoutMetrics.result()` dict
    ({view: {"paper", "dataset", "confusion", "images"}}).

    limit: score only the first `limit` ids of the split. with_probs: pass softmax probabilities
    so the result carries average precision. pred_out: also write the predicted layouts as a
    RackLay dataset there, at the dataset's layout size (so `racklay score` / `racklay show` read
    them beside it).
    shelf_length: every predicted shelf scaled to this known length (metres) before scoring.
    scale_from_truth: every predicted shelf scaled to its true shelf's length, so the score is of
    the shape alone (`racklay.layout.scale_shelves`)."""
    if shelf_length is not None and scale_from_truth:
        raise ValueError("give either a shelf length or scale_from_truth, not both")
    import torch

    from .data import RackLayRoot
    from .metrics import LayoutMetrics
    from .torchdata import data_loader

    pred = _predictor(weights, backend, threads)
    root, views, ds = split_dataset(pred, data, split, limit)
    loader = data_loader(ds, workers, batch_size=batch_size, shuffle=False)
    metrics = LayoutMetrics()
    out_root = RackLayRoot(pred_out) if pred_out is not None else None
    # saved at the dataset's own layout size, so `racklay score --pred OUT --gt DATA` reads them
    out_D = root.layout_shape(ds.ids[:20])[1] if out_root is not None else None
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(ds), desc=f"eval {split or 'all'}", unit="img", leave=False)
    shape = root.layout_shape(ds.ids[:20], views) if native else None
    draw = shape[1] if shape else None       # a struct model draws at the dataset's D
    with torch.inference_mode(), pred.drawing_at(draw):
        for batch in loader:
            classes, probs = pred.predict_batch(batch["image"])
            truth = {v: (np.stack([root.read_layouts(v, sid, R=pred.R) for sid in batch["id"]]) if native
                         else batch[v].numpy()) for v in views}
            if shelf_length is not None or scale_from_truth:
                classes, probs = _rescaled(classes, probs, truth, views, pred.grid, shelf_length)
            for v in views:
                c, p = classes[v], (probs[v] if with_probs else None)
                gt = truth[v]
                if native:
                    D = gt.shape[-1]
                    c = L.resize_layouts(c, D)
                    p = None if p is None else L.resize_layouts(p, D)
                metrics.update(v, c, gt, probs=p)
                if out_root is not None:
                    for sid, lay in zip(batch["id"], c if c.shape[-1] == out_D else L.resize_layouts(c, out_D)):
                        out_root.write_sample(sid, **{v: lay})
            if bar is not None:
                bar.update(len(batch["id"]))
    if bar is not None:
        bar.close()
    return metrics.result()


def _rescaled(classes: dict, probs: dict, truth: dict, views, grid: L.Grid, shelf_length: float | None):
    """A batch's predictions ({view: (N, R, S, S)}, probabilities {view: (N, R, 3, S, S)}) with every
    shelf scaled to `shelf_length` or, when it is None, to the length of the true shelf in the same
    channel (channels the truth lacks stay as predicted): `racklay.layout.scale_shelves` per image."""
    out_c = {v: np.empty_like(classes[v]) for v in views}
    out_p = {v: np.empty_like(probs[v]) for v in views}
    tgrid = L.Grid(size=truth[views[0]].shape[-1], extent=grid.extent)
    for j in range(len(classes[views[0]])):
        want = shelf_length
        if want is None:
            want = np.max([L.shelf_lengths(truth[v][j], tgrid) for v in views], axis=0)
            want = np.where(want > 0, want, np.nan)
        c, p, _ = L.scale_shelves({v: classes[v][j] for v in views}, grid, want, {v: probs[v][j] for v in views})
        for v in views:
            out_c[v][j], out_p[v][j] = c[v], p[v]
    return out_c, out_p


def eval_report(result: dict, weights, data, split, cfg=None, native: bool = False, scale: str = "model",
                gap_cut: bool = True, flip_average: bool = False) -> dict:
    """The JSON `racklay eval --json` writes: run description + the metrics dict."""
    views = [v for v in L.VIEWS if v in result]
    return {
        "weights": str(weights), "data": str(Path(data)), "split": split,
        "images": max((result[v]["images"] for v in views), default=0),
        "resolution": "dataset" if native else "model",
        "scale": scale,
        "gap_cut": gap_cut,
        "flip_average": flip_average,
        "model": cfg.to_dict() if cfg is not None else None,
        "metrics": result,
    }


def score_folders(pred_root, gt_root, split=None) -> tuple[dict, int]:
    """(metrics dict, images scored) for the predicted layouts in `pred_root` (a RackLay-format
    folder) against the ground-truth dataset `gt_root`: every id of `split`, or every predicted id.
    Every image scored needs a prediction in every view scored; anything missing is a ValueError
    naming the file (never a silently smaller denominator)."""
    from .data import RackLayRoot
    from .metrics import LayoutMetrics

    for root, what in ((pred_root, "predictions"), (gt_root, "ground-truth dataset")):
        if not os.path.isdir(root):
            raise ValueError(f"{root}: {what} folder not found")
    pred, gt = RackLayRoot(pred_root), RackLayRoot(gt_root)
    views = [v for v in pred.views() if v in gt.views()]
    if not views:
        raise ValueError(f"no common view: {pred.root} has {list(pred.views()) or 'no layouts'}, "
                         f"{gt.root} has {list(gt.views()) or 'no layouts'}")
    predicted = {view: set(pred.layout_ids(view)) for view in views}
    if split:
        ids = sorted(gt.resolve(split))
        if not ids:
            raise ValueError(f"{gt.root}: split {split!r} is empty")
    else:
        ids = sorted(set().union(*predicted.values()))
        if not ids:
            raise ValueError(f"{pred.root}: no predicted layouts to score")
    for view in views:
        missing = [i for i in ids if i not in predicted[view]]
        if missing:
            first = pred.layout_path(view, missing[0])
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise ValueError(f"{first}: prediction missing{more}; "
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
                raise ValueError(f"{gpath}: ground truth missing for predicted {view} layout {sid}")
            g = gt.read_layouts(view, sid, R=R, D=D)
            p = pred.read_layouts(view, sid, R=g.shape[0], D=g.shape[1])
            m.update(view, p, g)
    n = len(ids)
    return m.result(), n
