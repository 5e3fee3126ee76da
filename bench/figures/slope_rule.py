"""Regenerate docs/img/reasoning-slope-rule.jpg: the box stacks `racklay analyze` reads in a
front view without and with the slope rule (racklay.reasoning's `slope_fraction`), and told the
loads' width (`load_width_m`, `--load-width`), side by side.

    .venv/bin/python -m bench.figures.slope_rule [--photo PATH ...] [--weights FILE] [--out FILE]

One row per photo (the shipped model's front view of its lowest shelf) and a last row with a
ground-truth layout: a stack of four items, each narrower than the one below (what WareSynth
stacks), rasterised by racklay.layout. Dark outlines: the stacks read; their count in each
panel's title.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from bench.common import REPO
from racklay.predict import add_precision_args

#: a holdout photo (two sites no model trained on) and a test-site frame
PHOTOS = ("datasets/real-photos/138_loco2_three_loads_bay.jpg", "datasets/real-photos/111_palletvid0265_f123.jpg")


def cake():
    """Front layouts (R, D, D) of one shelf holding four items stacked narrower upward, and their grid."""
    from racklay import layout as L

    grid = L.Grid(256)
    shelf = L.Shelf(2.0, 0.8, 1.2)
    boxes = [L.Box(0.0, 0.0, 0.7 - 0.1 * k, 0.5, 0.2, z0=0.2 * k) for k in range(4)]
    top, front = L.stack_shelves([L.rasterize_shelf(shelf, boxes, grid)], 4, grid)
    return top, front, grid


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photo", action="append", default=None, help=f"photo; repeat for more (default: {', '.join(PHOTOS)})")
    ap.add_argument("--weights", default=None, help="model (default: the shipped one)")
    ap.add_argument("--load-width", type=float, default=0.8, help="the last column's load width, metres (default 0.8)")
    ap.add_argument("--out", default=str(REPO / "docs" / "img" / "reasoning-slope-rule.jpg"))
    add_precision_args(ap)
    args = ap.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from racklay.data import read_image
    from racklay.predict import Predictor
    from racklay.reasoning import ReasoningConfig, analyze_layouts
    from racklay.release import resolve_weights
    from racklay.viz import STACK_EDGE, colorize, content_window, save_figure

    pred = Predictor(str(resolve_weights(args.weights)), precision=args.precision)
    rows = []
    for path in [Path(p) for p in args.photo] if args.photo else [REPO / p for p in PHOTOS]:
        img = read_image(path)
        out = pred.predict(img)
        rows.append((img, path.name, out["top"], out["front"], out["grid"]))
    top, front, grid = cake()
    rows.append((None, "ground truth: four items stacked narrower upward", top, front, grid))

    on = ReasoningConfig()
    settings = (("without the slope rule", replace(on, slope_fraction=0.0)), (f"with it (slope_fraction {on.slope_fraction:g})", on),
                (f"loads {args.load_width:g} m wide", replace(on, load_width_m=args.load_width)))
    fig, axes = plt.subplots(len(rows), 4, figsize=(13.5, 2.6 * len(rows)), squeeze=False,
                             gridspec_kw={"width_ratios": [1.5, 1, 1, 1]})
    for r, (img, name, top, front, grid) in enumerate(rows):
        ax = axes[r, 0]
        if img is not None:
            ax.imshow(img)
        else:
            ax.text(0.5, 0.5, "(no photo)", ha="center", va="center", transform=ax.transAxes, fontsize=9)
        ax.set_title(name, fontsize=8)
        ax.set_axis_off()
        lo, hi = content_window([front[:1]])
        half = (hi - lo) / 2 * grid.res
        for c, (label, cfg) in enumerate(settings):
            ax = axes[r, c + 1]
            ax.imshow(colorize(front[0, lo:hi, lo:hi]), extent=(-half, half, -half, half), interpolation="nearest")
            shelf = next((s for s in analyze_layouts(top, front, grid, cfg).shelves if s.index == 0), None)
            for q in shelf.boxes if shelf else []:
                ax.add_patch(Rectangle((q.x[0], q.z[0]), q.x[1] - q.x[0], q.z[1] - q.z[0], fill=False,
                                       edgecolor=STACK_EDGE, linewidth=1.0))
            n = len(shelf.boxes) if shelf else 0
            ax.set_title(f"{label}: {n} stack{'' if n == 1 else 's'}", fontsize=8)
            ax.tick_params(labelsize=6)
    fig.suptitle("shelf 1, front view: the box stacks racklay analyze reads (outlined)", fontsize=10)
    fig.tight_layout()
    print(save_figure(fig, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
