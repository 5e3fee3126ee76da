"""Regenerate docs/img/waresynth_layout_extent.jpg: what WareSynth's layouts draw of the rack under
each `layout_extent` (bay / frame / row), on the same renders.

Renders N scenes of a recipe once per extent (same seed: the images are the same), picks the first
ones whose `row` layouts hold a neighbouring bay's load, and draws per scene the image, with the
part of the rack front that each extent draws marked at the height of the middle of its levels
(`frame` dashed, `row` solid; `bay` is the whole bay, also out of view), then the front layout
of the level that gains the most from `row` under each extent on one metric axis (metres along the rack from the considered bay's
centre: the layouts are re-centred on what they draw, the figure puts them back).

    .venv/bin/python -m bench.figures.layout_extent [--recipe mixed] [--n 48] [--rows 4]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.common import REPO

EXTENTS = ("bay", "frame", "row")
COLOURS = {"frame": "#f2c14e", "row": "#e4572e"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recipe", default="mixed")
    ap.add_argument("--n", type=int, default=48, help="scenes rendered per extent (default 48)")
    ap.add_argument("--rows", type=int, default=4, help="scenes in the figure (default 4)")
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--out", default=str(REPO / "docs" / "img" / "waresynth_layout_extent.jpg"))
    args = ap.parse_args(argv)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from racklay.cli import main as racklay_main
    from racklay.data import RackLayRoot, read_image
    from racklay.layout import BOX, Grid
    from racklay.synth.scene import Camera
    from racklay.viz import colorize, save_figure

    with tempfile.TemporaryDirectory() as tmp:
        roots = {}
        for ext in EXTENTS:
            roots[ext] = Path(tmp) / ext
            assert racklay_main(["synth", "--recipe", args.recipe, "--n", str(args.n), "--seed", str(args.seed),
                                 "--workers", "2", "--set", f"layout_extent={ext}", "--set", "layout_size=256",
                                 "--out", str(roots[ext]), "--no-progress"]) == 0
        ds = {ext: RackLayRoot(roots[ext]) for ext in EXTENTS}
        picked = []     # (id, {extent: meta}, {extent: front layouts}, the level to draw)
        for sid in ds["row"].ids():
            metas = {ext: json.loads((roots[ext] / "meta" / f"{sid}.json").read_text()) for ext in EXTENTS}
            if metas["row"]["rack"]["layout_row"] is None:
                continue
            fronts = {ext: ds[ext].read_layouts("front", sid) for ext in EXTENTS}
            # past the considered bay, with a neighbour's load on some level
            gain = [(fronts["row"][c] == BOX).any(axis=0).sum() - (fronts["frame"][c] == BOX).any(axis=0).sum()
                    for c in range(len(metas["row"]["shelf_board_tops"]))]
            if max(gain) > 4:
                picked.append((sid, metas, fronts, int(np.argmax(gain))))
            if len(picked) == args.rows:
                break
        if not picked:
            print(f"no scene of {args.n} draws a neighbouring bay's load: raise --n", file=sys.stderr)
            return 1

        fig, axes = plt.subplots(len(picked), 2, figsize=(11, 2.7 * len(picked)),
                                 gridspec_kw={"width_ratios": [1.35, 1]}, squeeze=False)
        for (sid, metas, fronts, k), (ax_im, ax_l) in zip(picked, axes):
            meta = metas["row"]
            windows = {ext: metas[ext]["rack"]["layout_window"] for ext in EXTENTS}
            grid = Grid(meta["grid"]["D"], meta["grid"]["extent_m"])
            cam = Camera.from_meta(meta)
            tops, heights = meta["shelf_board_tops"], meta["shelf_heights"]
            y_front, half = -meta["rack"]["depth"] / 2, meta["rack"]["length"] / 2
            ax_im.imshow(read_image(ds["row"].image_path(sid)))
            z = (tops[0] + tops[-1] + heights[-1]) / 2
            for ext in ("frame", "row"):
                w = windows[ext] or (-half, half)
                xs = np.linspace(w[0], w[1], 60)
                uv, depth = cam.image_points(np.c_[xs, np.full_like(xs, y_front), np.full_like(xs, z)])
                uv = uv[depth > 0.05] - 0.5          # pixel centres at +0.5
                off = 4 if ext == "row" else -4
                ax_im.plot(uv[:, 0], uv[:, 1] + off, color=COLOURS[ext], lw=2.5 if ext == "row" else 2,
                           ls="-" if ext == "row" else "--", label=f"{ext}: {w[1] - w[0]:.2f} m")
            ax_im.set_xlim(0, meta["image_size"][0])
            ax_im.set_ylim(meta["image_size"][1], 0)
            ax_im.axis("off")
            ax_im.legend(loc="lower right", fontsize=7, framealpha=0.8)
            ax_im.set_title(f"{args.recipe} {sid} ({meta['rack']['style']}, bay {2 * half:.2f} m)", fontsize=9)
            # one strip per extent (z from the board to the level's top), put back at its place along the rack
            hi = heights[k] + 0.1
            band = slice(int(grid.z_to_row(hi)), int(grid.z_to_row(0.0)))     # top row first
            x0, x1 = windows["row"]
            xlim = (min(-half, x0) - 0.6, max(half, x1) + 0.6)
            for i, ext in enumerate(EXTENTS):
                w = windows[ext]
                shift = 0.0 if w is None else (w[0] + w[1]) / 2
                y = (len(EXTENTS) - 1 - i) * (hi + 0.25)
                ax_l.imshow(colorize(fronts[ext][k][band]), origin="upper", interpolation="nearest",
                            extent=(shift - grid.extent / 2, shift + grid.extent / 2, y, y + hi))
                ax_l.text(xlim[0] + 0.05, y + hi / 2, ext, fontsize=8, va="center",
                          bbox={"facecolor": "white", "alpha": 0.8, "lw": 0})
            for b in (-half, half):
                ax_l.axvline(b, color="#555555", lw=0.8, ls=":")
            ax_l.set_xlim(*xlim)
            ax_l.set_ylim(-0.1, len(EXTENTS) * (hi + 0.25))
            ax_l.set_aspect("auto")
            ax_l.set_yticks([])
            ax_l.set_xlabel("x along the rack, m (dotted: the considered bay's ends)", fontsize=8)
            ax_l.set_title(f"shelf {k + 1}, front view: bay / frame / row", fontsize=9)
        fig.tight_layout()
        save_figure(fig, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
