"""Draw docs/img/convention.png: one shelf with two boxes in its top and front layouts, with the
axes of the layout convention annotated. Run: .venv/bin/python -m bench.figures.convention_figure"""
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import Patch

from bench.common import REPO
from racklay import layout as L
from racklay.viz import CLASS_NAMES, PALETTE, colorize, save_figure

grid = L.Grid(128, 4.0)  # zoomed grid for the picture; the convention is the same at 512 / 8 m
shelf = L.Shelf(length=2.4, depth=1.0, clear_height=0.8)
boxes = [L.Box(cx=-0.6, cy=-0.1, sx=0.6, sy=0.6, sz=0.5),
         L.Box(cx=0.55, cy=0.15, sx=0.5, sy=0.4, sz=0.3, z0=0.0, yaw=0.35)]
lay = L.rasterize_shelf(shelf, boxes, grid)
half = grid.extent / 2
fig, axes = plt.subplots(1, 2, figsize=(10, 5))
for ax, img, name, vlabel in ((axes[0], lay.top, "top view T_i", "y: depth, away from camera (far side up)"),
                              (axes[1], lay.front, "front view F_i", "z: up (board top on the centre row)")):
    ax.imshow(colorize(img), extent=(-half, half, -half, half), interpolation="nearest")
    ax.axhline(0, color="w", lw=0.5, ls=":")
    ax.axvline(0, color="w", lw=0.5, ls=":")
    ax.annotate("", xy=(1.6, -1.7), xytext=(0.4, -1.7), arrowprops=dict(arrowstyle="->", color="w"))
    ax.text(1.0, -1.6, "x", color="w", ha="center")
    ax.annotate("", xy=(-1.7, 1.6), xytext=(-1.7, 0.4), arrowprops=dict(arrowstyle="->", color="w"))
    ax.text(-1.6, 1.0, "y" if "top" in name else "z", color="w")
    ax.set_title(name)
    ax.set_xlabel("x: along the rack, to the right (m)")
    ax.set_ylabel(vlabel)
axes[0].text(0, 1.85, "back of the shelf", color="w", ha="center", fontsize=8)
axes[0].text(0, -1.95, "front edge (camera side)", color="w", ha="center", fontsize=8)
fig.legend(handles=[Patch(color=PALETTE[c] / 255, label=f"{c}: {CLASS_NAMES[c]} (file {int(L.FILE_VALUES[c])})")
                    for c in range(3)], loc="lower center", ncol=3, frameon=False)
fig.suptitle("Shelf-centric layouts: origin = centre of the board's top surface (shelf 2.4 x 1.0 m, clear 0.8 m; 4 m grid shown)")
fig.tight_layout(rect=(0, 0.06, 1, 0.95))
save_figure(fig, REPO / "docs" / "img" / "convention.png")
print("wrote docs/img/convention.png")
