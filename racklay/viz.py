"""Pictures of layouts: colour-coding and paper-style figures (photo + every shelf's top and
front layout). Uses matplotlib's Agg backend; nothing here opens a window."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from .layout import CLASS_NAMES, Grid

#: RGB colour per class id: background, shelf (free space), box (occupied)
PALETTE = np.array([[24, 24, 32], [70, 160, 230], [250, 150, 40]], dtype=np.uint8)
#: outline of a box stack read by racklay.reasoning (dark on the box colour, where stacks touch)
STACK_EDGE = "#202020"


def colorize(classes: np.ndarray) -> np.ndarray:
    """(…, D, D) class ids -> (…, D, D, 3) RGB uint8."""
    return PALETTE[np.asarray(classes, dtype=np.intp)]


def content_window(stacks: Sequence[np.ndarray], margin: float = 0.15, min_px: int = 32) -> tuple[int, int]:
    """A square window [lo, hi) around the centre that holds every non-background pixel of all
    given layout stacks (symmetric about the centre, so both views keep the shared x axis)."""
    D = stacks[0].shape[-1]
    half = min_px // 2
    for s in stacks:
        nz = np.nonzero(np.asarray(s).reshape(-1, D, D).max(axis=0))
        if nz[0].size:
            ext = max(np.abs(nz[0] + 0.5 - D / 2).max(), np.abs(nz[1] + 0.5 - D / 2).max())
            half = max(half, int(np.ceil(ext * (1 + margin))))
    half = min(half, D // 2)
    return D // 2 - half, D // 2 + half


def layout_figure(image: np.ndarray | None, top: np.ndarray | None, front: np.ndarray | None,
                  out: str | os.PathLike | None = None, title: str = "", grid: Grid | None = None,
                  crop: bool = True, dpi: int = 110, outline_stacks: bool = False,
                  load_width: float | None = None):
    """Paper-style figure: the photo on the left, then one column per shelf (lowest first) with
    its top view above its front view. `outline_stacks`: outline every box stack that the rack
    reasoning reads in these layouts (racklay.reasoning.analyze_layouts, its defaults), so stacks
    that touch are told apart; `load_width`: read with the loads' width known (`load_width_m`).
    Returns the matplotlib Figure (closed after saving when `out` is given)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch, Rectangle

    stacks = [s for s in (top, front) if s is not None]
    if not stacks:
        raise ValueError("nothing to draw: give top and/or front layouts")
    R, D = stacks[0].shape[0], stacks[0].shape[-1]
    grid = grid or Grid(size=D)
    lo, hi = content_window(stacks) if crop else (0, D)
    half_m = (hi - lo) / 2 * grid.res
    analysis = None
    if outline_stacks:
        from .reasoning import ReasoningConfig, analyze_layouts

        analysis = analyze_layouts(top, front, grid, ReasoningConfig(load_width_m=load_width or 0.0))
    rows = [("top", top), ("front", front)]
    rows = [(n, s) for n, s in rows if s is not None]
    ncols = R + (1 if image is not None else 0)
    W, H = 2.1 * R + (3.6 if image is not None else 0), 2.2 * len(rows) + 0.7
    fig = plt.figure(figsize=(W, H))
    # fixed margins in inches (tight_layout measured every tick label and took half the time of
    # `racklay predict` per photo): room for the y labels left, titles above, x labels and the
    # legend below
    gs = fig.add_gridspec(len(rows), ncols, width_ratios=([1.7] if image is not None else []) + [1] * R,
                          left=0.1 / W if image is not None else 0.55 / W, right=1 - 0.1 / W,
                          bottom=0.68 / H, top=1 - (0.6 if title else 0.3) / H, wspace=0.38, hspace=0.32)
    if image is not None:
        ax = fig.add_subplot(gs[:, 0])
        ax.imshow(image)
        ax.set_axis_off()
        ax.set_title("input")
    extent = (-half_m, half_m, -half_m, half_m)
    off = 1 if image is not None else 0
    for ri, (name, stack) in enumerate(rows):
        for i in range(R):
            ax = fig.add_subplot(gs[ri, off + i])
            ax.imshow(colorize(stack[i, lo:hi, lo:hi]), extent=extent, interpolation="nearest")
            shelf = next((sh for sh in analysis.shelves if sh.index == i), None) if analysis else None
            for q in (shelf.boxes if shelf else []):
                v = q.y if name == "top" else q.z
                if v[1] > v[0] and q.x[1] > q.x[0]:
                    ax.add_patch(Rectangle((q.x[0], v[0]), q.x[1] - q.x[0], v[1] - v[0], fill=False,
                                           edgecolor=STACK_EDGE, linewidth=0.8))
            ax.set_title(f"shelf {i + 1} {name}", fontsize=9)
            ax.tick_params(labelsize=6)
            ax.locator_params(nbins=5)     # at most ~5 ticks: labels never touch
            if i == 0:
                ax.set_ylabel("y (m, far up)" if name == "top" else "z (m, up)", fontsize=7)
            if ri == len(rows) - 1:
                ax.set_xlabel("x (m)", fontsize=7)
    handles = [Patch(color=PALETTE[c] / 255, label=CLASS_NAMES[c]) for c in range(3)]
    if analysis is not None:
        handles.append(Patch(fill=False, edgecolor=STACK_EDGE, label="box stack read (racklay analyze"
                             + (f", loads {load_width:g} m wide)" if load_width else ")")))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    if out is not None:
        save_figure(fig, out, dpi=dpi)
    return fig


def save_figure(fig, out: str | os.PathLike, dpi: int = 110) -> Path:
    """Save a matplotlib figure atomically (PNG by the file's suffix) and close it."""
    import io

    import matplotlib.pyplot as plt

    from .atomic import atomic_write_bytes

    out = Path(out)
    buf = io.BytesIO()
    fig.savefig(buf, format=out.suffix.lstrip(".") or "png", dpi=dpi)
    plt.close(fig)
    return atomic_write_bytes(out, buf.getvalue())


def contact_sheet(rows: Sequence[tuple], out: str | os.PathLike, row_h: int = 168,
                  title: str = "") -> Path:
    """One PNG with a row per photo: the photo, then for every shelf (lowest first) its top view
    above its front view, cropped to a window shared by the row's layouts (`content_window`).
    `rows`: (name, image RGB uint8, top (R, D, D) | None, front (R, D, D) | None)."""
    import cv2

    from .atomic import atomic_save_png

    if not rows:
        raise ValueError("contact sheet: no rows")
    tile = row_h // 2
    photo_w = int(row_h * 1.6)
    R = max((s.shape[0] for _, _, t, f in rows for s in (t, f) if s is not None), default=1)
    pad, label_h = 6, 16
    width = pad + photo_w + pad + R * (tile + pad)
    head = 28 if title else 0
    sheet = np.full((head + label_h + len(rows) * (row_h + label_h + pad) + pad, width, 3), 255, np.uint8)

    def text(img, s, x, y, scale=0.42):
        cv2.putText(img, s, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (20, 20, 20), 1, cv2.LINE_AA)

    if title:
        text(sheet, title, pad, 20, 0.55)
    y0 = head
    for i in range(R):
        text(sheet, f"shelf {i + 1}: top / front", pad + photo_w + pad + i * (tile + pad), y0 + 12, 0.32)
    y0 += label_h
    for name, image, top, front in rows:
        text(sheet, str(name), pad, y0 + 12)
        y = y0 + label_h
        h, w = image.shape[:2]
        s = min(row_h / h, photo_w / w)
        ph, pw = max(1, round(h * s)), max(1, round(w * s))
        sheet[y:y + ph, pad:pad + pw] = cv2.resize(image, (pw, ph), interpolation=cv2.INTER_AREA)
        stacks = [a for a in (top, front) if a is not None]
        lo, hi = content_window(stacks) if stacks else (0, 1)
        for r in range(R):
            x = pad + photo_w + pad + r * (tile + pad)
            for k, stack in enumerate((top, front)):
                yy = y + k * tile
                if stack is None or r >= stack.shape[0]:
                    sheet[yy:yy + tile - 2, x:x + tile] = 235
                    continue
                rgb = colorize(stack[r, lo:hi, lo:hi])
                sheet[yy:yy + tile - 2, x:x + tile] = cv2.resize(rgb, (tile, tile - 2), interpolation=cv2.INTER_NEAREST)
        y0 += row_h + label_h + pad
    out = Path(out)
    atomic_save_png(out, sheet)
    return out
