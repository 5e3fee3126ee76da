"""Does a struct model read a rack's metric scale from the image, or guess it from the training prior?

    .venv/bin/python -m bench.accuracy.scale_cues --weights W --data ROOT [--split test] [--n 400]

A single image fixes a rack's metric size only through things of known size: under a pinhole camera
a rack k times larger seen from k times farther is the same picture. In WareSynth's `complex` and
`complex_paper` the bay length (1.6-3.0 m), depth, level spacing and the lens all vary, and the camera
frames the levels it looks at, so what is left to read the scale from is the boxes (category sizes
within +-12 %) and the level spacing's range. `structure_oracle.py` showed the scale is most of the
distance to the paper's Table 1 on those recipes; this script asks whether the model reads it at all.

For the first N images of a split it takes the model's structure (front view: shelf length; top
view: shelf depth) and the truth's (`truth_structure` of the dataset's layouts), one value per image
(the median over the shelves both have), and prints:

- slope: the least-squares slope of log predicted on log true size over the images. 1 reads the
  scale; 0 predicts one size whatever the rack (the prior); R² how much of the true size's spread
  it explains;
- the median error of the model, beside that of the best constant (the images' median true size,
  a guess that knows the test distribution): what reading the image buys over the prior;
- the same by how full the image's shelves are (the truth's share of positions along the shelf
  where a box stands): on an empty shelf only the level spacing and the rack itself are left;
- the same by how many of the shelf's two ends the image shows (the lowest labelled level's span,
  `racklay.data.level_spans`, which WareSynth writes), and by how many the model places in the
  frame (its placement, `racklay.structure.image_span`: what `racklay predict` reports; an end
  within `racklay.predict.FRAME_EDGE_MARGIN` of the frame's edge counts as cut): where the
  frame cuts the shelf, its length is not in the image and can only be inferred from what stands
  on it;
- the median signed error by focal length (from the WareSynth meta, where there is one): a model
  that takes a long lens for a large rack has a bias that grows with the focal length; and the
  median error once its linear trend in log focal is removed (fitted on the same images: what a
  known focal length could remove at most, linearly).

`--iou` also scores the layouts (drawn at the data's resolution) on the images whose frame shows
both ends of every labelled level and on the others. `--plot PNG` draws predicted against true
size, one dot per image coloured by how many ends of its shelf the frame shows, with the line a
perfect reading would follow and the best constant's.

Torch backend, struct models only; precision follows the machine. Prints numbers; asserts nothing.
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from bench.common import add_struct_split_args, open_struct_split, table1_cells, table1_header
from racklay.data import level_spans
from racklay.metrics import LayoutMetrics
from racklay.predict import decide, ends_cut
from racklay.structure import HARD_TAU_PX, image_span, rasterize, truth_structure

#: (view, structure field, what it is) of each size this script reads
SIZES = (("front", "length", "shelf length"), ("top", "extent", "shelf depth"))
#: rows of the shelf-ends table: how many of the shelf's two ends the image shows
ENDS = ((2, "both ends in the frame"), (1, "one end"), (0, "neither (the frame cuts both)"))
#: the image groups of `--iou` (`framing_of`)
FRAMING = {"in": "both ends of every level in the frame", "cut": "the frame cuts a level",
           "unknown": "no level spans in the meta"}
#: bins of the image's box fill (share of positions along its shelves where a box stands)
FILL_BINS = ((0.0, 0.05, "empty (< 5 %)"), (0.05, 0.4, "partly (5-40 %)"), (0.4, 1.01, "full (>= 40 %)"))


def ends_in_frame(span) -> float:
    """How many ends (0-2) of a shelf spanning `span` (left, right; image widths) the frame shows,
    by `racklay predict`'s rule (`racklay.predict.ends_cut`); NaN for an unknown span."""
    cut = ends_cut(span)
    return math.nan if cut is None else float(2 - sum(cut))


def framing_of(spans: np.ndarray) -> str:
    """An image's framing from its levels' spans ((R, 2), NaN where none): "in" when the frame shows
    both ends of every labelled level, "cut" when it cuts one, "unknown" without spans."""
    cuts = [ends_cut(sp) for sp in spans if np.isfinite(sp).all()]
    return "unknown" if not cuts else ("cut" if any(any(c) for c in cuts) else "in")


def fit(true_log: np.ndarray, pred_log: np.ndarray) -> dict:
    """Slope and R² of pred_log ~ a + b true_log, the median |pred / true - 1| and the best
    constant's (exp of the median true_log), in %."""
    out = {"n": len(true_log), "model": 100 * np.median(np.abs(np.expm1(pred_log - true_log))),
           "constant": 100 * np.median(np.abs(np.expm1(np.median(true_log) - true_log)))}
    if len(true_log) >= 3 and np.ptp(true_log) > 0:
        out["slope"] = np.polyfit(true_log, pred_log, 1)[0]
        out["r2"] = np.corrcoef(true_log, pred_log)[0, 1] ** 2
    return out


def row(label: str, f: dict) -> str:
    slope = f"{f['slope']:.2f}" if "slope" in f else "-"
    r2 = f"{f['r2']:.2f}" if "r2" in f else "-"
    return f"| {label} | {f['n']} | {slope} | {r2} | {f['model']:.1f} % | {f['constant']:.1f} % |"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_struct_split_args(ap, "RackLay dataset root (WareSynth meta gives the focal length and the level spans)")
    ap.add_argument("--plot", default=None, metavar="PNG", help="also draw predicted against true size (a PNG)")
    ap.add_argument("--iou", action="store_true",
                    help="also score the layouts (drawn at the data's resolution, as `racklay eval --native`) "
                         "on the images whose frame shows both ends of every labelled level and on the others")
    args = ap.parse_args(argv)

    pred, root, views, ds = open_struct_split(args)
    sizes = [s for s in SIZES if s[0] in views]
    extent = pred.grid.extent
    rows = {v: [] for v, _, _ in sizes}   # per image: log true, log predicted, box fill, focal, ends in frame
    groups = {g: LayoutMetrics() for g in FRAMING}
    counts = dict.fromkeys(FRAMING, 0)
    for s in range(0, len(ds), args.batch_size):
        items = [ds[i] for i in range(s, min(s + args.batch_size, len(ds)))]
        ids = ds.ids[s:s + len(items)]
        structs = pred.structures(torch.stack([it["image"] for it in items]))
        metas = [root.read_meta(sid) or {} for sid in ids]
        spans = np.stack([level_spans(m, pred.R, str(root.meta_path(sid))) for m, sid in zip(metas, ids)])
        framing = [framing_of(sp) for sp in spans]
        for g in framing:
            counts[g] += 1
        gts = {v: np.stack([root.read_layouts(v, sid, R=pred.R) for sid in ids]) for v in views}
        if args.iou:
            for v in views:
                gt = gts[v]
                classes = decide(rasterize(v, structs[v], gt.shape[-1], extent, HARD_TAU_PX).numpy())
                for j, g in enumerate(framing):
                    groups[g].update(v, classes[j:j + 1], gt[j:j + 1])
        for v, field, _ in sizes:
            gt = gts[v]
            st = structs[v]
            tr = truth_structure(v, torch.from_numpy(gt.astype(np.int64)), extent, st["box"].shape[-1])
            both = (tr["presence"] & (st["presence"].float() > 0)).numpy()
            pspan = image_span(st).numpy()
            for j, sid in enumerate(ids):
                k = np.nonzero(both[j])[0]
                if not len(k):
                    continue
                true = np.median([float(tr[field][j, i]) for i in k])
                got = np.median([float(st[field][j, i]) for i in k])
                fill = float(np.mean([tr["box"][j, i].float().mean() for i in np.nonzero(tr["presence"][j].numpy())[0]]))
                K = (metas[j].get("camera") or {}).get("K")
                rows[v].append((math.log(true), math.log(got), fill, float(K[0][0]) if K else math.nan,
                                ends_in_frame(spans[j, k.min()]), ends_in_frame(pspan[j, k.min()])))
        print(f"\r{s + len(items)} / {len(ds)} images", end="", flush=True)
    print(f"\n{pred.weights} on {root.root} [{args.split}], {len(ds)} images; one value per image "
          "(the median over the shelves the model and the truth both have)")
    for v, field, what in sizes:
        a = np.array(rows[v]).reshape(-1, 6)
        if not len(a):
            print(f"\n{what} ({v} view): no shelf both the model and the truth have")
            continue
        t, p, fill, focal, ends, pends = a.T
        print(f"\n{what} ({v} view): true {np.exp(t.min()):.2f}-{np.exp(t.max()):.2f} m, median {np.exp(np.median(t)):.2f} m")
        print("| images | n | slope (1 reads, 0 guesses) | R² | median error, model | median error, best constant |")
        print("|---|---|---|---|---|---|")
        print(row("all", fit(t, p)))
        for lo, hi, label in FILL_BINS:
            m = (fill >= lo) & (fill < hi)
            if m.any():
                print(row(f"shelves {label}", fit(t[m], p[m])))
        for n, label in ENDS:
            m = ends == n
            if m.any():
                print(row(label, fit(t[m], p[m])))
        for n, label in ENDS:
            m = pends == n
            if m.any():
                print(row(f"model places {label}", fit(t[m], p[m])))
        if np.isfinite(ends).all():
            print("ends in the frame, truth (rows) against the model's placement (columns 2 / 1 / 0): "
                  + "; ".join(f"{n}: " + " / ".join(str(int(((ends == n) & (pends == q)).sum())) for q in (2, 1, 0))
                              for n in (2, 1, 0)))
        if np.isfinite(focal).all() and np.ptp(focal) > 0:
            edges = np.quantile(focal, [0, 1 / 3, 2 / 3, 1])
            bins = np.clip(np.searchsorted(edges, focal, side="right") - 1, 0, 2)
            print("| focal length (px) | n | median signed error (predicted / true - 1) |")
            print("|---|---|---|")
            for b in range(3):
                m = bins == b
                print(f"| {focal[m].min():.0f}-{focal[m].max():.0f} | {m.sum()} | "
                      f"{100 * np.expm1(np.median(p[m] - t[m])):+.1f} % |")
            e = p - t                     # log error; its linear trend in log focal, fitted on these images
            b, a = np.polyfit(np.log(focal), e, 1)
            print(f"error ∝ focal^{b:.2f}; the median error with that trend removed (fitted on these images: "
                  f"what knowing the focal length could remove, linearly): "
                  f"{100 * np.median(np.abs(np.expm1(e - a - b * np.log(focal)))):.1f} % "
                  f"(as predicted {100 * np.median(np.abs(np.expm1(e))):.1f} %)")
    if args.iou:
        print("\nlayouts by framing, drawn at the data's resolution: paper-protocol mIoU (a channel empty in both "
              "scores 1, so images of fewer levels score higher: compare groups by the dataset level), dataset-level IoU")
        print(table1_header("images | n", views))
        for g, label in FRAMING.items():
            if counts[g]:
                vals = table1_cells(groups[g].result(), views)
                print(f"| {label} | {counts[g]} | " + " | ".join(f"{x:.2f}" for x in vals) + " |")
    if args.plot:
        print(f"wrote {plot(rows, sizes, args.plot, f'{pred.weights.parent.name} on {root.root.name} [{args.split}]')}")
    return 0


def plot(rows: dict, sizes, out, title: str):
    """Predicted against true size per view, one dot per image coloured by how many ends of its
    shelf the frame shows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from racklay.viz import save_figure

    colours = {2: "tab:blue", 1: "tab:orange", 0: "tab:red"}
    fig, axes = plt.subplots(1, len(sizes), figsize=(5.2 * len(sizes), 5.0), squeeze=False, layout="constrained")
    for ax, (v, _, what) in zip(axes[0], sizes):
        a = np.array(rows[v]).reshape(-1, 6)
        true, got, ends = np.exp(a[:, 0]), np.exp(a[:, 1]), a[:, 4]
        for n, label in ENDS:
            m = ends == n
            if m.any():
                ax.scatter(true[m], got[m], s=9, color=colours[n], label=f"{label} ({m.sum()})")
        if np.isnan(ends).any():
            m = np.isnan(ends)
            ax.scatter(true[m], got[m], s=9, color="grey", label=f"ends unknown ({m.sum()})")
        lo, hi = min(true.min(), got.min()) * 0.95, max(true.max(), got.max()) * 1.05
        ax.plot([lo, hi], [lo, hi], "k-", lw=1, label="reads the scale (predicted = true)")
        ax.axhline(np.median(true), color="grey", ls="--", lw=1, label="best constant (guesses)")
        ax.set_aspect("equal")
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_xlabel(f"true {what} (m)")
        ax.set_ylabel(f"predicted {what} (m)")
        ax.set_title(f"{what}, {v} view ({len(a)} images)")
        ax.legend(loc="upper left", fontsize=7)
    fig.suptitle(title, fontsize=9)
    return save_figure(fig, out)


if __name__ == "__main__":
    raise SystemExit(main())
