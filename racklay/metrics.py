"""Layout metrics: the paper's protocol and honest dataset-level numbers.

Paper protocol (what RackLay's Table 1 reports): for every image and every shelf channel, and
for each class k in {shelf ("rack"), box}, compare the binary masks pred == k and gt == k:
IoU = |P & G| / |P | G| and pixel precision = |P & G| / |P|. A channel where the class is absent
from both prediction and truth counts as 1 for both numbers; a channel with an empty prediction
but a non-empty truth has precision 0. Both are averaged over images x channels. The paper calls
the second number "mAP"; it is pixel precision, and this module labels it so.

Dataset level: a 3 x 3 confusion matrix per view accumulated over every pixel of every channel
gives IoU, precision and recall per class (an all-background prediction scores 0 here, whereas
the paper protocol gives it ~42/53). When class probabilities are available, average precision
per class comes from score histograms (streaming, 1000 bins), i.e. area under the
precision-recall curve of the pixel classifier "is class k".

Separate boxes (front view): shelf channels whose truth holds two or more box runs along x, how
many of them the prediction separates too, and how many with its gaps where the truth's are
(`racklay.layout.separated_shelves`), counted over channels and over images.

Shelves found (per view): a shelf channel holds a shelf when any of its pixels is not background;
per image, whether the prediction holds as many shelves as the truth, fewer or more, and of the
images whose truth holds two or more shelves, in how many the prediction holds at least as many
(a model that merges or misses a level of a multi-level rack shows here before it shows in IoU).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .layout import BOX, CLASS_NAMES, GAP_TOLERANCE, NUM_CLASSES, SHELF, VIEWS, separated_shelves

EVAL_CLASSES = {"rack": SHELF, "box": BOX}
#: the counts of `separated_shelves` kept per view (front only), in this order
SEPARATION_KEYS = ("truth", "separated", "placed", "predicted")
#: the per-image shelf-count comparison kept per view, in this order (`shelf_counts`)
SHELF_COUNT_KEYS = ("equal", "fewer", "more", "multi", "multi_found")


def shelf_counts(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-image shelf-count comparison of (N, R, D, D) class ids, summed over the images, in
    SHELF_COUNT_KEYS order: images whose prediction holds as many shelves as the truth, fewer,
    more; images whose truth holds >= 2 shelves, and of those the ones the prediction holds at
    least as many shelves as the truth. A channel holds a shelf when any pixel is not background."""
    n_pred = (pred.reshape(*pred.shape[:2], -1) > 0).any(-1).sum(1)
    n_gt = (gt.reshape(*gt.shape[:2], -1) > 0).any(-1).sum(1)
    multi = n_gt >= 2
    return np.array([(n_pred == n_gt).sum(), (n_pred < n_gt).sum(), (n_pred > n_gt).sum(),
                     multi.sum(), (multi & (n_pred >= n_gt)).sum()], np.int64)


def paper_scores(pred: np.ndarray, gt: np.ndarray, cls: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel IoU and pixel precision of class `cls`. pred, gt: (..., D, D) class ids.
    Returns two arrays of shape pred.shape[:-2]."""
    p = pred == cls
    g = gt == cls
    inter = np.count_nonzero(p & g, axis=(-2, -1)).astype(np.float64)
    union = np.count_nonzero(p | g, axis=(-2, -1)).astype(np.float64)
    npred = np.count_nonzero(p, axis=(-2, -1)).astype(np.float64)
    iou = np.where(union > 0, inter / np.maximum(union, 1), 1.0)
    prec = np.where(npred > 0, inter / np.maximum(npred, 1), np.where(union > 0, 0.0, 1.0))
    return iou, prec


def confusion(pred: np.ndarray, gt: np.ndarray, n: int = NUM_CLASSES) -> np.ndarray:
    """n x n confusion matrix, rows = truth, columns = prediction."""
    idx = gt.astype(np.int64).ravel() * n + pred.astype(np.int64).ravel()
    return np.bincount(idx, minlength=n * n).reshape(n, n)


@dataclass
class _ViewAcc:
    iou: dict = field(default_factory=lambda: {k: [] for k in EVAL_CLASSES})
    prec: dict = field(default_factory=lambda: {k: [] for k in EVAL_CLASSES})
    cm: np.ndarray = field(default_factory=lambda: np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64))
    # score histograms for AP: [class][positive?][bin]
    hist: np.ndarray | None = None
    images: int = 0
    # separate boxes (front view): [shelf channels, images] x SEPARATION_KEYS
    sep: np.ndarray = field(default_factory=lambda: np.zeros((2, len(SEPARATION_KEYS)), np.int64))
    # shelves found: SHELF_COUNT_KEYS
    shelves: np.ndarray = field(default_factory=lambda: np.zeros(len(SHELF_COUNT_KEYS), np.int64))


class LayoutMetrics:
    """Accumulate predictions batch by batch, then `result()`.

    update(view, pred, gt, probs=None): pred and gt are class-id arrays (N, R, D, D) (or
    (R, D, D) for one image); probs, if given, are (N, R, 3, D, D) class probabilities.
    """

    def __init__(self, bins: int = 1000):
        self.bins = bins
        self.views: dict[str, _ViewAcc] = {}

    def update(self, view: str, pred: np.ndarray, gt: np.ndarray, probs: np.ndarray | None = None) -> None:
        if view not in VIEWS:
            raise ValueError(f"view must be one of {VIEWS}, got {view!r}")
        pred = np.asarray(pred)
        gt = np.asarray(gt)
        if pred.shape != gt.shape:
            raise ValueError(f"{view}: prediction shape {pred.shape} != ground truth shape {gt.shape}")
        if pred.ndim == 3:
            pred, gt = pred[None], gt[None]
            probs = None if probs is None else np.asarray(probs)[None]
        acc = self.views.setdefault(view, _ViewAcc())
        acc.images += pred.shape[0]
        for name, cls in EVAL_CLASSES.items():
            iou, prec = paper_scores(pred, gt, cls)
            acc.iou[name].append(iou.ravel())
            acc.prec[name].append(prec.ravel())
        acc.cm += confusion(pred, gt)
        acc.shelves += shelf_counts(pred, gt)
        if view == "front":
            sep = separated_shelves(gt, pred)
            parts = (sep.truth, sep.hit, sep.placed, sep.pred)
            acc.sep[0] += [int(x.sum()) for x in parts]
            acc.sep[1] += [int(x.any(-1).sum()) for x in parts]
        if probs is not None:
            probs = np.asarray(probs, dtype=np.float32)
            if acc.hist is None:
                acc.hist = np.zeros((NUM_CLASSES, 2, self.bins), np.int64)
            for cls in (SHELF, BOX):
                s = probs[:, :, cls]
                b = np.minimum((s * self.bins).astype(np.int64), self.bins - 1).ravel()
                pos = (gt == cls).ravel()
                acc.hist[cls, 1] += np.bincount(b[pos], minlength=self.bins)
                acc.hist[cls, 0] += np.bincount(b[~pos], minlength=self.bins)

    def result(self) -> dict:
        out: dict = {}
        for view, acc in self.views.items():
            r: dict = {"images": acc.images, "paper": {}, "dataset": {}}
            for name, cls in EVAL_CLASSES.items():
                iou = np.concatenate(acc.iou[name]) if acc.iou[name] else np.zeros(0)
                prec = np.concatenate(acc.prec[name]) if acc.prec[name] else np.zeros(0)
                r["paper"][name] = {"mIoU": float(iou.mean()) if iou.size else float("nan"),
                                    "pixel_precision": float(prec.mean()) if prec.size else float("nan")}
            for cls, (cname, d) in enumerate(confusion_scores(acc.cm).items()):
                if acc.hist is not None and cls != 0:
                    d["AP"] = average_precision_from_hist(acc.hist[cls, 1], acc.hist[cls, 0])
                r["dataset"][cname] = d
            r["confusion"] = acc.cm.tolist()
            r["shelf_count"] = dict(zip(SHELF_COUNT_KEYS, map(int, acc.shelves)))
            if view == "front":
                r["separation"] = {unit: dict(zip(SEPARATION_KEYS, map(int, row)))
                                   for unit, row in zip(("shelves", "images"), acc.sep)}
            out[view] = r
        return out


def confusion_scores(cm) -> dict[str, dict[str, float]]:
    """Dataset-level IoU, precision and recall per class (by name) from a confusion matrix
    (rows = truth, columns = prediction); matrices of several runs may be summed first."""
    cm = np.asarray(cm, dtype=np.float64)
    tp = np.diag(cm)
    out = {}
    for cls, cname in enumerate(CLASS_NAMES):
        fp = cm[:, cls].sum() - tp[cls]
        fn = cm[cls, :].sum() - tp[cls]
        out[cname] = {"IoU": _div(tp[cls], tp[cls] + fp + fn), "precision": _div(tp[cls], tp[cls] + fp),
                      "recall": _div(tp[cls], tp[cls] + fn)}
    return out


def _div(a: float, b: float) -> float:
    return float(a / b) if b > 0 else float("nan")


def average_precision_from_hist(pos: np.ndarray, neg: np.ndarray) -> float:
    """AP (area under the step precision-recall curve) from per-bin counts of positive and
    negative scores; thresholds sweep from the highest bin down."""
    tp = np.cumsum(pos[::-1]).astype(np.float64)
    fp = np.cumsum(neg[::-1]).astype(np.float64)
    total = tp[-1] if tp.size else 0
    if total == 0:
        return float("nan")
    precision = tp / np.maximum(tp + fp, 1)
    recall = tp / total
    d_recall = np.diff(np.concatenate([[0.0], recall]))
    return float((precision * d_recall).sum())


def format_tables(result: dict, title: str = "") -> str:
    """The paper's Table-1 layout (x100) and the dataset-level table, as Markdown."""
    lines = []
    if title:
        lines += [f"### {title}", ""]
    views = [v for v in VIEWS if v in result]
    lines.append("Paper protocol (per image x shelf, empty-in-both = 1), mIoU / pixel precision "
                 "(the paper labels the latter 'mAP'):")
    lines.append("")
    hdr = " | ".join(f"{v} {k}" for v in views for k in EVAL_CLASSES)
    lines.append(f"| {hdr} |")
    lines.append("|" + "---|" * (len(views) * len(EVAL_CLASSES)))
    cells = [f"{100 * result[v]['paper'][k]['mIoU']:.2f} / {100 * result[v]['paper'][k]['pixel_precision']:.2f}"
             for v in views for k in EVAL_CLASSES]
    lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("Dataset level (confusion matrix over all pixels), x100:")
    lines.append("")
    lines.append("| view | class | IoU | precision | recall | AP |")
    lines.append("|---|---|---|---|---|---|")
    for v in views:
        for cname in ("shelf", "box"):
            d = result[v]["dataset"][cname]
            ap = d.get("AP")
            lines.append(f"| {v} | {cname} | {_pct(d['IoU'])} | {_pct(d['precision'])} | "
                         f"{_pct(d['recall'])} | {_pct(ap) if ap is not None else 'n/a'} |")
    found = shelves_found(result)
    if found:
        v, c = found
        lines += ["", f"Shelves found ({v} view): the prediction holds as many shelves as the truth in {c['equal']} "
                      f"of {result[v]['images']} images, fewer in {c['fewer']}, more in {c['more']}; all of them "
                      f"in {c['multi_found']} of the {c['multi']} images whose truth holds two or more."]
    sep = result.get("front", {}).get("separation")
    if sep:
        c, i = sep["shelves"], sep["images"]
        lines += ["", f"Separate boxes (front view): the truth holds two or more box runs on {c['truth']} shelves "
                      f"({i['truth']} images); the prediction separates {c['separated']} of them, "
                      f"{c['placed']} with its gaps where the truth's are (within {GAP_TOLERANCE:.0%} of the shelf's length), "
                      f"and separates {c['predicted']} shelves in all."]
    return "\n".join(lines)


def shelves_found(result: dict) -> tuple[str, dict] | None:
    """(view, `shelf_count` counts) that a report quotes from a `LayoutMetrics.result()`: the
    front view's, else the first view's (both views draw the same shelves), or None."""
    views = [v for v in VIEWS if v in result and result[v].get("shelf_count")]
    if not views:
        return None
    v = "front" if "front" in views else views[0]
    return v, result[v]["shelf_count"]


def _pct(x: float) -> str:
    return "nan" if x is None or np.isnan(x) else f"{100 * x:.2f}"
