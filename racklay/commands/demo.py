"""racklay demo: the main job end to end (synthetic -> real transfer, see transfer/demo.py);
`--toy` keeps the quick schematic demo of the data/metrics layer (seconds, no training)."""
from __future__ import annotations

from pathlib import Path

from racklay.cli import at_least


def register(sub) -> None:
    from transfer.commands.demo import DESCRIPTION, add_demo_args

    p = sub.add_parser(
        "demo", help="the main job end to end: shipped model on real photos, sim -> real fine-tune (<10 min; --toy: seconds)",
        description=DESCRIPTION + " With --toy instead: build a small schematic dataset with the layout "
                    "module, validate it with check-data, score a degraded copy of its layouts against "
                    "the truth, and write a paper-style figure (seconds, no training).")
    add_demo_args(p)
    p.add_argument("--toy", action="store_true", help="the quick schematic demo of the data/metrics layer")
    p.add_argument("--n", type=at_least(1), default=24, help="--toy: number of schematic samples (default 24)")
    p.set_defaults(func=run)


def run(args) -> int:
    if not args.toy:
        from transfer.commands.demo import run as transfer_demo

        return transfer_demo(args)
    if args.out == "outputs/transfer-demo":
        args.out = "outputs/demo"
    return run_toy(args)


def run_toy(args) -> int:
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
