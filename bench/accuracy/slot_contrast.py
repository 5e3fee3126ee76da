"""How dark the slot between two loads is, against the loads beside it: renders and labelled photos.

A model can only learn to separate loads from how a gap between them looks. On the labelled
photos of pallet racking the gaps are dark slots; the eighth session found the renders' gaps
easy (the bright back wall seen through the slot) and no model of the project finding the
photos' gaps. This measures it: for every gap between two box runs on a shelf's front view (the
front layout, as the model is scored), the mean luminance of the slot's face (the front plane
between the two runs, from 10 % to 90 % of the lower run's height, its middle 70 % across) over
the mean luminance of the two runs' faces beside it (as wide as the gap, 10-30 cm), measured in
the image through the scene's own mapping of that plane: the camera for renders, the labelled
rack's homography for photos. Below 1 the slot is darker than its loads.

    .venv/bin/python -m bench.accuracy.slot_contrast --data /work/data/ab-mx-d21 --data /work/data/ab-ao-d21 \
        [--photos datasets/real-photos [--photo-split datasets/real-photos/SOURCES.tsv:test]] [--limit 300]
        [--figure slots.png]

Prints per set the number of gaps measured, the quartiles of the ratio and the share of slots
darker than 0.6 times their loads, overall and for gaps of at least 8 cm. Numbers only.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from racklay.data import luminance

#: gaps measured: between MIN_GAP_M and MAX_GAP_M wide (narrower: loads touching; wider: an empty stretch)
MIN_GAP_M, MAX_GAP_M, WIDE_GAP_M = 0.02, 0.40, 0.08
#: a slot's face must cover this many image pixels to be measured
MIN_PIXELS = 6
DARK = 0.6
#: images per set in the --figure contact sheet
FIGURE_ROWS = 4


def front_gaps(front: np.ndarray, grid) -> list[tuple[float, float, float]]:
    """(x0, x1, height) in metres of every gap between two box runs of one front-view channel
    (classes, D x D): the runs' columns are those with a box above the board, the height the
    lower of the two runs' heights at the gap's edges."""
    from racklay.layout import BOX

    D = front.shape[0]
    above = front[: D // 2] == BOX                 # rows above the board, top row first
    cols = above.any(axis=0)
    top = np.where(cols, np.argmax(above, axis=0), D // 2)
    idx = np.flatnonzero(cols)
    out = []
    for a, b in zip(idx[:-1], idx[1:]):
        if b - a > 1:                              # columns a+1 .. b-1 hold no box
            x0, x1 = grid.col_span_to_x(a + 1, b)
            if MIN_GAP_M <= x1 - x0 <= MAX_GAP_M:
                out.append((x0, x1, float(grid.px_to_m(D // 2 - max(top[a], top[b])))))
    return out


def region_mean(Y: np.ndarray, poly: np.ndarray) -> float | None:
    """Mean of Y over an image polygon (None: too small, outside the image or not finite)."""
    import cv2

    if not np.all(np.isfinite(poly)):
        return None
    mask = np.zeros(Y.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(poly).astype(np.int32)], 1)
    n = int(mask.sum())
    return float(Y[mask > 0].mean()) if n >= MIN_PIXELS else None


def slot_ratios(Y: np.ndarray, fronts: np.ndarray, grid, outline_of,
                canvas: np.ndarray | None = None) -> list[tuple[float, float]]:
    """(gap width, slot / loads luminance ratio) for every measurable gap of one image;
    `outline_of(k)(x0, x1, z0, z1)` is the image polygon of a rectangle on channel k's front
    plane (x along the shelf, z above its board). With a
    `canvas` (the RGB image), each measured slot is outlined on it in red, its loads' faces in
    green, the ratio written above."""
    import cv2

    out = []
    for k in range(fronts.shape[0]):
        gaps = front_gaps(fronts[k], grid)
        if not gaps:
            continue
        outline = outline_of(k)
        for x0, x1, h in gaps:
            w = x1 - x0
            f = float(np.clip(w, 0.10, 0.30))
            z0, z1 = 0.1 * h, 0.9 * h
            polys = [outline(a, b, z0, z1) for a, b in ((x0 + 0.15 * w, x1 - 0.15 * w), (x0 - f, x0 - 0.1 * f), (x1 + 0.1 * f, x1 + f))]
            slot, left, right = (region_mean(Y, p) for p in polys)
            if slot is None or left is None or right is None:
                continue
            ratio = slot / max((left + right) / 2, 1.0)
            out.append((w, ratio))
            if canvas is not None:
                t = max(1, round(canvas.shape[1] / 300))
                for p, c in zip(polys, ((255, 0, 0), (0, 220, 0), (0, 220, 0))):
                    cv2.polylines(canvas, [np.round(p).astype(np.int32)], True, c, t)
                x, y = np.round(polys[0].min(axis=0)).astype(int)
                cv2.putText(canvas, f"{ratio:.2f}", (x, max(y - 4 * t, 10 * t)), cv2.FONT_HERSHEY_SIMPLEX,
                            0.35 * t, (255, 255, 0), t, cv2.LINE_AA)
    return out


def render_ratios(root: Path, limit: int, sheet: list | None = None) -> list[tuple[float, float]]:
    """Every gap of a WareSynth set's front layouts, through each render's camera and lens; the
    first FIGURE_ROWS images with a measured gap, outlined, appended to `sheet` (contact-sheet rows)."""
    from racklay.data import RackLayRoot, read_image
    from racklay.layout import Grid
    from racklay.synth.scene import Camera

    ds = RackLayRoot(root)
    ids = ds.ids()[:limit]
    out = []
    for sid in ids:
        meta = json.loads((root / "meta" / f"{sid}.json").read_text())
        grid = Grid(meta["grid"]["D"], meta["grid"]["extent_m"])
        cam = Camera.from_meta(meta)
        y_front = -meta["rack"]["depth"] / 2
        window = meta["rack"].get("layout_window")           # `frame` layouts are re-centred on it
        shift = 0.0 if window is None else (window[0] + window[1]) / 2
        tops = meta["shelf_board_tops"]
        fronts = ds.read_layouts("front", sid)
        rgb = read_image(ds.image_path(sid))
        Y = luminance(rgb)

        def outline_of(k, tops=tops, cam=cam, y_front=y_front, shift=shift):
            def f(x0, x1, z0, z1):
                z = tops[k] + np.array([z0, z0, z1, z1])
                uv, depth = cam.image_points(np.c_[np.array([x0, x1, x1, x0]) + shift, np.full(4, y_front), z])
                if np.any(depth <= 0.05):
                    return np.full((4, 2), np.nan)
                return uv - 0.5        # pixel centres at +0.5
            return f

        out += _measure(Y, fronts[: len(tops)], grid, outline_of, rgb, f"{root.name}/{sid}", sheet)
    return out


def photo_ratios(project_dir: Path, names: set | None, sheet: list | None = None) -> list[tuple[float, float]]:
    """Every gap of the labelled photos' front layouts, through each photo's rack homography (and
    the first FIGURE_ROWS photos with a measured gap, outlined, appended to `sheet`)."""
    from annotate import geometry as G
    from annotate.dataset import annotation_layouts
    from annotate.store import DONE_STATUSES, Project
    from racklay import layout as L

    project = Project(project_dir, create=False)
    grid = L.Grid(project.settings["D"], project.settings["extent"])
    out, unlabelled = [], []
    for name in project.images():
        if names is not None and name not in names:
            continue
        ann = project.load(name)
        if ann.get("status") not in DONE_STATUSES:
            unlabelled.append(name)
            continue
        try:
            _, fronts, scene = annotation_layouts(project, ann)
        except G.GeometryError as e:
            raise SystemExit(f"{project.annotation_path(name)}: {e}") from None
        rgb = project.read_image(name)
        Y = luminance(rgb)

        def outline_of(k, scene=scene):
            def f(x0, x1, z0, z1):
                v = scene.shelf_v[k]
                return G.rect_outline(scene.plane, L.x_to_u(x0, scene.width), L.x_to_u(x1, scene.width), v + z0, v + z1)
            return f

        out += _measure(Y, fronts[: len(scene.shelf_v)], grid, outline_of, rgb, name, sheet)
    if unlabelled:
        print(f"{project_dir}: {len(unlabelled)} photo(s) not labelled done, not measured: "
              f"{', '.join(unlabelled[:5])}{' ...' if len(unlabelled) > 5 else ''}", file=sys.stderr)
    return out


def _measure(Y, fronts, grid, outline_of, rgb, name, sheet):
    """slot_ratios of one image; while `sheet` (this set's contact-sheet rows) holds fewer than
    FIGURE_ROWS rows, an image with a measured gap is added to it, outlined."""
    if sheet is None or len(sheet) >= FIGURE_ROWS:
        return slot_ratios(Y, fronts, grid, outline_of)
    canvas = rgb[..., :3].copy()
    r = slot_ratios(Y, fronts, grid, outline_of, canvas)
    if r:
        sheet.append((name, canvas, None, fronts))
    return r


def summary(name: str, ratios: list[tuple[float, float]]) -> str:
    def row(sel):
        r = np.array([v for w, v in ratios if sel(w)])
        if not len(r):
            return "0 gaps |  |  |  | "
        q = np.percentile(r, [25, 50, 75])
        return f"{len(r)} | {q[0]:.2f} | {q[1]:.2f} | {q[2]:.2f} | {100 * np.mean(r < DARK):.0f} %"
    return (f"| {name} | {row(lambda w: True)} | {row(lambda w: w >= WIDE_GAP_M)} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", action="append", default=[], help="a WareSynth (RackLay-format) set with meta (repeat)")
    ap.add_argument("--limit", type=int, default=300, help="first N samples of each set (default 300)")
    ap.add_argument("--photos", default=None, help="an annotate project of labelled photos")
    ap.add_argument("--figure", default=None, metavar="PNG",
                    help=f"also draw a contact sheet: the first {FIGURE_ROWS} images of each set with a measured "
                         "gap, each slot outlined in red, its loads' faces in green, the ratio above, and the "
                         "image's front layouts beside it")
    ap.add_argument("--photo-split", default=None, metavar="TSV:SPLIT",
                    help="only the photos of this split of a split file (e.g. datasets/real-photos/SOURCES.tsv:test)")
    args = ap.parse_args(argv)
    if not args.data and not args.photos:
        ap.error("give --data and/or --photos")
    for d in args.data:
        if not (Path(d) / "meta").is_dir():
            ap.error(f"{d}: not a WareSynth set (no meta/ folder)")
    rows, sheet = [], []
    for d in args.data:
        p, mine = Path(d), [] if args.figure else None
        rows.append(summary(f"`{p.name}` (first {args.limit})", render_ratios(p, args.limit, mine)))
        sheet += mine or []
    if args.photos:
        names, label = None, "photos"
        if args.photo_split:
            from annotate.dataset import read_split_file

            tsv, _, split = args.photo_split.rpartition(":")
            names = {n for n, s in read_split_file(tsv).items() if s == split}
            label = f"photos, split {split}"
        mine = [] if args.figure else None
        rows.append(summary(f"{label} ({args.photos})", photo_ratios(Path(args.photos), names, mine)))
        sheet += mine or []
    head = ("slot / loads luminance: gaps | 25 % | median | 75 % | darker than "
            f"{DARK} | gaps >= {WIDE_GAP_M * 100:.0f} cm | 25 % | median | 75 % | darker than {DARK}")
    print("| set | " + head + " |")
    print("|---" * (head.count("|") + 2) + "|")
    print("\n".join(rows))
    if args.figure and sheet:
        from racklay.viz import contact_sheet

        print(f"figure: {contact_sheet(sheet, args.figure, title='slot (red) / loads (green) luminance')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
