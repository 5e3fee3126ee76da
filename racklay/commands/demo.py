"""racklay demo: the main job on an embedded default."""
from __future__ import annotations

from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "demo", help="run the end-to-end demo on built-in data",
        description="Build a small schematic dataset with the layout module, validate it with "
                    "check-data, score a degraded copy of its layouts against the truth, and write a "
                    "paper-style figure. Prints where every output went.")
    p.add_argument("--out", default="outputs/demo", help="output folder (default: outputs/demo)")
    p.add_argument("--n", type=int, default=24, help="number of samples (default 24)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from racklay import layout as L
    from racklay.atomic import atomic_write_json
    from racklay.commands.score import score_roots
    from racklay.data import RackLayRoot, check_dataset
    from racklay.metrics import format_tables
    from racklay.toy import build_toy_dataset
    from racklay.viz import layout_figure

    out = Path(args.out)
    data = out / "toy-dataset"
    print(f"[1/4] building {args.n} schematic samples (exact layouts from racklay.layout) -> {data}")
    ds = build_toy_dataset(data, n=args.n, seed=args.seed)
    print("[2/4] validating")
    rep = check_dataset(data)
    print("      " + rep.summary())
    if not rep.ok:
        for line in rep.problems:
            print("      " + line)
        return 1
    print("[3/4] scoring a degraded copy (boxes eroded, one shelf dropped per image) against the truth")
    pred = RackLayRoot(out / "degraded-predictions")
    rng = np.random.default_rng(args.seed)
    import cv2
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
    result, n = score_roots(pred.root, data)
    print(format_tables(result, title=f"degraded copy vs truth, {n} images"))
    atomic_write_json(out / "scores.json", result)
    fig = out / "figure.png"
    print(f"[4/4] figure -> {fig}")
    sid = ds.ids()[0]
    layout_figure(ds.read_image(sid), ds.read_layouts("top", sid), ds.read_layouts("front", sid), out=fig,
                  title=f"schematic sample {sid} (exact layouts)")
    print(f"outputs: dataset {data}, predictions {pred.root}, scores {out / 'scores.json'}, figure {fig}")
    return 0
