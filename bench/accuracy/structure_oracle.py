"""Which part of a struct model's structure limits its score: each part swapped for the truth's.

    .venv/bin/python -m bench.accuracy.structure_oracle --weights W --data ROOT [--split test] [--n 400]

A struct model predicts, per shelf and view, a structure (racklay.structure): presence, metric
length and extent (the scale), per position along the shelf whether a box stands there, and the
box's height (front view) or depth interval (top view) as fractions of the shelf (the shape). This
scores the model's own structures on N images of a split (the first N), then the same structures
with one or more parts replaced by the truth's structure of the same shelf (`truth_structure` of
the dataset's layouts), drawn at the dataset's own resolution and scored there (the paper-protocol
mIoU of Table 1 and the dataset-level IoU, as `racklay eval --native`):

- scale: the true presence, length and extent (each also alone); image scale: every shelf of an
  image scaled by one factor, the median of true / predicted length over its shelves (what one
  known dimension, `--shelf-length`, can fix; the rest of the scale error is per shelf);
- boxes: the true box / no box at each position (along the model's shelf when its scale is kept);
- sizes: the true height or depth interval where a box stands;
- and combinations; all three is the structure's own ceiling (the truth drawn back).

The gain of a row over the model's is what a perfect estimate of that part alone would buy: the
part whose oracle gains most is where training or design effort pays. Torch backend, struct models
only; precision follows the machine. Prints numbers; asserts nothing.
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from bench.common import add_struct_split_args, open_struct_split, table1_cells, table1_header
from racklay.metrics import LayoutMetrics
from racklay.predict import decide
from racklay.structure import HARD_TAU_PX, rasterize, truth_structure

#: the parts of a structure an oracle can take from the truth
SCALE = ("presence", "length", "extent")
#: each oracle's parts replaced by the truth's
ORACLES = {
    "model": (),
    "presence": ("presence",),
    "length": ("length",),
    "extent": ("extent",),
    "image scale": ("image scale",),
    "scale": SCALE,
    "boxes": ("boxes",),
    "sizes": ("sizes",),
    "scale + boxes": SCALE + ("boxes",),
    "boxes + sizes": ("boxes", "sizes"),
    "scale + boxes + sizes": SCALE + ("boxes", "sizes"),
}
#: a logit that `rasterize` reads as certain
_SURE = 30.0


def with_truth(view: str, st: dict, tr: dict, parts) -> dict:
    """The predicted structure `st` of one view with `parts` (of ORACLES) taken from the truth `tr`
    (`truth_structure`, same T). Only the fields `rasterize` draws are kept; the back interval of a
    `--struct-back` model is dropped when sizes come from the truth (whose interval spans every box
    of the column)."""
    keys = ["presence", "length", "extent", "box"] + (["height"] if view == "front" else ["near", "far"])
    if view == "top" and "back" in st and "sizes" not in parts:
        keys += ["back", "back_near", "back_far"]
    out = {k: st[k].float() for k in keys}
    if "image scale" in parts:   # one factor per image: what a known dimension (--shelf-length) fixes
        ratio = torch.where(tr["presence"], tr["length"] / out["length"].clamp_min(1e-3), torch.nan)
        k = ratio.nanmedian(dim=1).values.nan_to_num(1.0).unsqueeze(1)
        out["length"], out["extent"] = out["length"] * k, out["extent"] * k
    if "presence" in parts:
        out["presence"] = torch.where(tr["presence"], _SURE, -_SURE)
    for k in ("length", "extent"):
        if k in parts:    # a shelf the truth lacks keeps the model's size
            out[k] = torch.where(tr["presence"], tr[k], out[k])
    if "boxes" in parts:
        out["box"] = torch.where(tr["box"], _SURE, -_SURE)
    if "sizes" in parts:
        for k in ("height",) if view == "front" else ("near", "far"):
            out[k] = torch.where(tr["box"], tr[k], out[k])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_struct_split_args(ap)
    args = ap.parse_args(argv)

    pred, root, views, ds = open_struct_split(args)
    extent = pred.grid.extent
    metrics = {name: LayoutMetrics() for name in ORACLES}
    T = None
    errs = {v: [] for v in views}     # per shelf drawn where the truth has one: log(pred / true) length, extent, image
    for s in range(0, len(ds), args.batch_size):
        items = [ds[i] for i in range(s, min(s + args.batch_size, len(ds)))]
        structs = pred.structures(torch.stack([it["image"] for it in items]))
        for v in views:
            gt = np.stack([root.read_layouts(v, sid, R=pred.R) for sid in ds.ids[s:s + len(items)]])
            D = gt.shape[-1]
            T = structs[v]["box"].shape[-1]
            tr = truth_structure(v, torch.from_numpy(gt.astype(np.int64)), extent, T)
            both = tr["presence"] & (structs[v]["presence"].float() > 0)
            for j, k in zip(*np.nonzero(both.numpy())):
                errs[v].append([math.log(float(structs[v][q][j, k]) / float(tr[q][j, k])) for q in ("length", "extent")]
                               + [s + j])
            for name, parts in ORACLES.items():
                st = with_truth(v, structs[v], tr, parts)
                # numpy's argmax (`decide`): torch's over the class axis of (B, R, 3, 512, 512) was 4/5 of the run
                classes = decide(rasterize(v, st, D, extent, HARD_TAU_PX).numpy())
                metrics[name].update(v, classes, gt)
        print(f"\r{s + len(items)} / {len(ds)} images", end="", flush=True)
    print("scale error of the shelves both the model and the truth have: median |predicted / true - 1|, "
          "as predicted and after one factor per image (the median length ratio of its shelves, as `image scale`; "
          "an image of one shelf keeps no length error)")
    print("| view | shelves | length | extent | length, image factor removed | extent, image factor removed |")
    print("|---|---|---|---|---|---|")
    for v in views:
        e = np.array(errs[v]).reshape(-1, 3)
        img = e[:, 2].astype(int)
        factor = {i: np.median(e[img == i, 0]) for i in np.unique(img)}
        f = np.array([factor[i] for i in img])
        pct = [100 * np.median(np.abs(np.expm1(x))) for x in (e[:, 0], e[:, 1], e[:, 0] - f, e[:, 1] - f)]
        print(f"| {v} | {len(e)} | " + " | ".join(f"{x:.1f} %" for x in pct) + " |")
    print(f"\n{pred.weights} on {root.root} [{args.split}], {len(ds)} images, drawn at the data's "
          f"resolution ({D} x {D}, T = {T} positions per shelf)")
    print(table1_header("structure", views))
    base = None
    for name, m in metrics.items():
        vals = table1_cells(m.result(), views)
        base = vals if base is None else base
        cells = [f"{x:.2f}" if name == "model" else f"{x:.2f} ({x - b:+.2f})" for x, b in zip(vals, base)]
        print(f"| {name} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
