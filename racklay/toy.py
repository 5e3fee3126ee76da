"""A tiny schematic dataset built straight from the layout module: random racks and boxes,
their exact layouts, and a flat orthographic drawing of the rack's front as the "image".

It needs no renderer, so tests of every issue and the schematic demo (`toy_demo`, run by
`transfer demo --toy`) can use it. It is not a
substitute for WareSynth's rendered images: the picture is a schematic, and it says so.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from . import layout as L
from .data import RackLayRoot, make_splits


def random_rack(rng: np.random.Generator, R: int = L.DEFAULT_R):
    """Random shelves (bottom-up) and boxes: returns (length, depth, heights, list[list[Box]])."""
    n = int(rng.integers(1, R + 1))
    length = float(rng.uniform(1.2, 2.6))
    depth = float(rng.uniform(0.5, 1.0))
    heights = [float(rng.uniform(0.35, 0.7)) for _ in range(n)]
    shelves = []
    for h in heights:
        boxes, x = [], -length / 2 + float(rng.uniform(0.02, 0.2))
        density = rng.uniform(0, 1)
        while True:
            sx = float(rng.uniform(0.2, 0.5))
            if x + sx > length / 2:
                break
            if rng.uniform() < density:
                sy = float(rng.uniform(0.3, depth))
                sz = float(rng.uniform(0.15, h * 0.9))
                cy = float(rng.uniform(-(depth - sy) / 2, (depth - sy) / 2))
                boxes.append(L.Box(cx=x + sx / 2, cy=cy, sx=sx, sy=sy, sz=sz))
            x += sx + float(rng.uniform(0.03, 0.15))
        shelves.append(boxes)
    return length, depth, heights, shelves


def schematic_image(length, heights, shelves, size=(280, 470), rng=None) -> np.ndarray:
    """Orthographic front drawing: steel uprights and boards, boxes as brown rectangles."""
    import cv2

    H, W = size
    rng = rng or np.random.default_rng(0)
    img = np.full((H, W, 3), rng.integers(150, 210), np.uint8)
    total = sum(heights) + 0.05 * (len(heights) + 1)
    scale = min((W - 40) / length, (H - 20) / total)
    x0 = W / 2 - length / 2 * scale
    z = H - 10
    for h, boxes in zip(heights, shelves):
        cv2.rectangle(img, (int(x0), int(z - 0.05 * scale)), (int(x0 + length * scale), int(z)), (40, 70, 160), -1)
        base = z - 0.05 * scale
        for b in boxes:
            a, c = b.x_range()
            p0 = (int(x0 + L.x_to_u(a, length) * scale), int(base - (b.z0 + b.sz) * scale))
            p1 = (int(x0 + L.x_to_u(c, length) * scale), int(base - b.z0 * scale))
            col = tuple(int(v) for v in rng.integers([150, 100, 50], [200, 140, 80]))
            cv2.rectangle(img, p0, p1, col, -1)
            cv2.rectangle(img, p0, p1, (60, 40, 20), 1)
        z = base - h * scale
    cv2.rectangle(img, (int(x0 - 6), int(z)), (int(x0), H - 10), (40, 70, 160), -1)
    cv2.rectangle(img, (int(x0 + length * scale), int(z)), (int(x0 + length * scale + 6), H - 10), (40, 70, 160), -1)
    return img


def build_toy_dataset(root, n: int = 24, seed: int = 0, R: int = L.DEFAULT_R, D: int = 128,
                      extent: float = L.DEFAULT_EXTENT_M, splits=None) -> RackLayRoot:
    """Write `n` schematic samples with exact layouts and train/val/test splits to `root`."""
    rng = np.random.default_rng(seed)
    grid = L.Grid(D, extent)
    ds = RackLayRoot(root)
    ids = []
    for i in range(n):
        length, depth, heights, shelves = random_rack(rng, R)
        per = [L.rasterize_shelf(L.Shelf(length, depth, h), boxes, grid) for h, boxes in zip(heights, shelves)]
        top, front = L.stack_shelves(per, R, grid)
        sid = f"{i:06d}"
        ds.write_sample(sid, image=schematic_image(length, heights, shelves, rng=rng), top=top, front=front,
                        meta={"source": "toy schematic", "shelf_heights": heights, "rack_length": length,
                              "rack_depth": depth, "grid": {"D": D, "extent_m": extent},
                        # 3D truth per visible shelf (lowest first), for validating rack reasoning
                        "shelves": [{"length": length, "depth": depth, "clear_height": h,
                                     "boxes": [dataclasses.asdict(b) for b in boxes]}
                                    for h, boxes in zip(heights, shelves)]})
        ids.append(sid)
    for name, part in make_splits(ids, splits or {"train": 0.6, "val": 0.2, "test": 0.2}, seed).items():
        ds.write_split(name, part)
    return ds


def toy_demo(out, n: int = 24, seed: int = 0, log=print) -> int:
    """The seconds-long schematic demo of the data and metrics layer: build `n` schematic samples,
    validate them with check-data, score a degraded copy of their layouts against the truth and
    draw a paper-style figure, all under `out`. Returns an exit code (1: the dataset has problems)."""
    import cv2

    from .atomic import atomic_write_json
    from .data import check_dataset
    from .evaluate import score_folders
    from .metrics import format_tables
    from .viz import layout_figure

    out = Path(out)
    data = out / "toy-dataset"
    log(f"[1/4] building {n} schematic samples (exact layouts from racklay.layout) -> {data}")
    ds = build_toy_dataset(data, n=n, seed=seed)
    log("[2/4] validating")
    rep = check_dataset(data)
    log("      " + rep.summary())
    if not rep.ok:
        for line in rep.problems:
            log("      " + line)
        return 1
    log("[3/4] scoring a degraded copy (boxes eroded, one shelf dropped per image) against the truth")
    pred = RackLayRoot(out / "degraded-predictions")
    rng = np.random.default_rng(seed)
    for sid in ds.ids():
        lay = {}
        for v in ("top", "front"):
            a = ds.read_layouts(v, sid)
            for c in range(a.shape[0]):
                box = cv2.erode((a[c] == L.BOX).astype(np.uint8), np.ones((3, 3), np.uint8))
                a[c][(a[c] == L.BOX) & (box == 0)] = L.SHELF
            lay[v] = a
        drop = int(rng.integers(0, L.visible_shelf_count(lay["top"]) or 1))
        lay["top"][drop] = 0
        pred.write_sample(sid, top=lay["top"], front=lay["front"])
    result, scored = score_folders(pred.root, data)
    log(format_tables(result, title=f"degraded copy vs truth, {scored} images"))
    atomic_write_json(out / "scores.json", result)
    fig = out / "figure.png"
    log(f"[4/4] figure -> {fig}")
    sid = ds.ids()[0]
    layout_figure(ds.read_image(sid), ds.read_layouts("top", sid), ds.read_layouts("front", sid), out=fig,
                  title=f"schematic sample {sid} (exact layouts)")
    log(f"outputs: dataset {data}, predictions {pred.root}, scores {out / 'scores.json'}, figure {fig}")
    return 0
