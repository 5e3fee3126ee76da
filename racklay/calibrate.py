"""Decision calibration: choose, per view, the logit biases that turn the model's scores into the
classes that score best on a validation split.

A network trained with pixel cross-entropy on layouts that are ~99 % background ranks pixels well
(its box average precision is far above its box IoU) but its plain argmax under-calls the rare
classes: a box on a shelf is scored "shelf" when it is not sure. Like choosing a detector's score
threshold, `fit_decision_bias` picks additive biases for the shelf and box logits (background
fixed at 0) that maximise the mean of the dataset-level shelf and box IoU on a split the model
was not trained on, and stores them in the model config (`ModelConfig.decision_bias`), where
`racklay.predict.Predictor` applies them. Probabilities, and so average precision, are unchanged.

How: one pass over the split collects, per view and ground-truth class, a 2-D histogram of the
logit differences (shelf − background, box − background) at 1/16 resolution. The class chosen for
any bias pair depends only on those two differences, so every candidate pair on the grid is scored
from the histograms without running the model again.

    racklay calibrate --weights runs/x/best.safetensors --data datasets/release --split val --out calibrated.safetensors
"""
from __future__ import annotations

import os
from dataclasses import dataclass, replace

import numpy as np

from .layout import NUM_CLASSES

#: histogram range and resolution of the logit differences (values outside are clipped to the ends)
DIFF_RANGE = 10.0
BINS_PER_UNIT = 16
#: candidate biases for shelf and box (background stays 0): a coarse grid over -2 ... 6 in steps
#: of 0.25, then steps of 1/16 within ±0.25 of the coarse best
BIAS_RANGE = (-2.0, 6.0)
COARSE_STEP, FINE_STEP = 0.25, 0.0625


@dataclass
class ViewCalibration:
    view: str
    bias: tuple            # (background, shelf, box)
    before: dict           # {"shelf_iou", "box_iou", "score"} with plain argmax
    after: dict            # the same with `bias`


class DiffHistogram:
    """Per ground-truth class counts of (shelf − bg, box − bg) logit differences."""

    def __init__(self):
        self.n = int(2 * DIFF_RANGE * BINS_PER_UNIT)
        self.counts = np.zeros((NUM_CLASSES, self.n, self.n), dtype=np.int64)
        # (3, n, n) logits (0, shelf−bg, box−bg) at the bin centres: what `decide` sees for each bin
        c = (np.arange(self.n) + 0.5) / BINS_PER_UNIT - DIFF_RANGE
        self.centres = np.zeros((NUM_CLASSES, self.n, self.n), dtype=np.float32)
        self.centres[1] = c[:, None]
        self.centres[2] = c[None, :]

    def _index(self, d: np.ndarray) -> np.ndarray:
        i = np.floor((d + DIFF_RANGE) * BINS_PER_UNIT).astype(np.int64)
        return np.clip(i, 0, self.n - 1)

    def update(self, logits: np.ndarray, gt: np.ndarray) -> None:
        """logits (N, R, 3, S, S), gt (N, R, S, S) class ids."""
        z = np.asarray(logits, dtype=np.float32)
        i = self._index(z[:, :, 1] - z[:, :, 0]).ravel()
        j = self._index(z[:, :, 2] - z[:, :, 0]).ravel()
        g = np.asarray(gt).astype(np.int64).ravel()
        flat = (g * self.n + i) * self.n + j
        self.counts += np.bincount(flat, minlength=self.counts.size).reshape(self.counts.shape)

    def scores(self, bias) -> dict:
        """Dataset-level shelf / box IoU (percent) and their mean for one bias triple."""
        from .predict import decide

        cls = decide(self.centres, bias, axis=0)
        conf = np.stack([np.bincount(cls.ravel(), weights=self.counts[g].ravel(), minlength=NUM_CLASSES)
                         for g in range(NUM_CLASSES)])          # conf[gt, pred]
        out = {}
        for k, name in ((1, "shelf_iou"), (2, "box_iou")):
            union = conf[k].sum() + conf[:, k].sum() - conf[k, k]
            out[name] = 100.0 * conf[k, k] / union if union else 0.0
        out["score"] = (out["shelf_iou"] + out["box_iou"]) / 2
        return out

    def best(self) -> tuple[tuple, dict]:
        """The shelf / box biases with the highest mean IoU: a coarse grid over BIAS_RANGE, then a
        fine one around its best (ties keep the earlier, i.e. smaller, biases)."""
        best_bias, best = (0.0, 0.0, 0.0), self.scores(None)

        def search(c1, c2):
            nonlocal best_bias, best
            for b1 in c1:
                for b2 in c2:
                    bias = (0.0, round(float(b1), 4), round(float(b2), 4))
                    s = self.scores(bias)
                    if s["score"] > best["score"] + 1e-9:
                        best_bias, best = bias, s

        lo, hi = BIAS_RANGE
        coarse = np.arange(lo, hi + 1e-9, COARSE_STEP)
        search(coarse, coarse)
        fine = np.arange(-COARSE_STEP, COARSE_STEP + 1e-9, FINE_STEP)
        search(np.clip(best_bias[1] + fine, lo, hi), np.clip(best_bias[2] + fine, lo, hi))
        return best_bias, best

def fit_decision_bias(predictor, data, split: str | None = "val", batch_size: int = 8, limit: int | None = None,
                      progress: bool = True) -> list[ViewCalibration]:
    """Fit per-view decision biases for `predictor` (a `racklay.predict.Predictor`) on `split` of the
    RackLay dataset at `data` (scored at the model's layout size, as in training)."""
    import torch
    from torch.utils.data import DataLoader

    from .evaluate import split_dataset

    _, views, ds = split_dataset(predictor, data, split, limit)
    hists = {v: DiffHistogram() for v in views}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(ds), desc=f"calibrate on {split or 'all'}", unit="img", leave=False)
    with torch.inference_mode():
        for batch in DataLoader(ds, batch_size=batch_size, shuffle=False):
            logits = predictor.logits(batch["image"])
            for v in views:
                hists[v].update(logits[v], batch[v].numpy())
            if bar is not None:
                bar.update(len(batch["id"]))
    if bar is not None:
        bar.close()
    out = []
    for v in views:
        bias, after = hists[v].best()
        current = (predictor.cfg.decision_bias or {}).get(v)   # "before": the model's decision as it is
        out.append(ViewCalibration(v, bias, hists[v].scores(current), after))
    return out


def calibrated_config(cfg, fits: list[ViewCalibration]):
    """`cfg` with the fitted biases as its decision_bias."""
    return replace(cfg, decision_bias={f.view: f.bias for f in fits})


def write_calibrated(weights: str | os.PathLike, out: str | os.PathLike, fits: list[ViewCalibration],
                     data: str | os.PathLike, split: str | None) -> str:
    """Copy the checkpoint `weights` to `out` with the fitted biases in its config and the fit in
    its metadata (`calibration`). The model weights are copied unchanged (dtype included)."""
    from .checkpoint import load_checkpoint, save_checkpoint
    from .model import RackLayNet

    ck = load_checkpoint(weights)
    cfg = calibrated_config(ck.cfg, fits)
    sd = ck.section("model")
    model = RackLayNet(ck.cfg)
    dtype = next(iter(sd.values())).dtype if sd else None
    if dtype is not None and dtype.is_floating_point:
        model = model.to(dtype)
    model.load_state_dict(sd, strict=True)
    meta = dict(ck.meta)
    meta["calibration"] = {"data": str(data), "split": split,
                           "views": {f.view: {"bias": list(f.bias), "before": f.before, "after": f.after}
                                     for f in fits}}
    return str(save_checkpoint(out, model, cfg, extra=meta))


def format_fits(fits: list[ViewCalibration]) -> str:
    lines = [f"{'view':<6} {'bias bg/shelf/box':>20}   {'shelf IoU':>16}   {'box IoU':>16}   {'mean':>14}",
             f"{'':<6} {'':>20}   {'before → after':>16}   {'before → after':>16}   {'before → after':>14}"]
    for f in fits:
        b = "/".join(f"{x:+.3g}" for x in f.bias)
        lines.append(f"{f.view:<6} {b:>20}   {f.before['shelf_iou']:6.2f} → {f.after['shelf_iou']:6.2f}   "
                     f"{f.before['box_iou']:6.2f} → {f.after['box_iou']:6.2f}   "
                     f"{f.before['score']:5.2f} → {f.after['score']:5.2f}")
    return "\n".join(lines)
