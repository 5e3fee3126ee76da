"""Does telling the model which rack to read help? (`racklay predict --rack-box`, RULE18 in
docs/results/2026-12-06-fifty-second-session.md)

    .venv/bin/python -m bench.accuracy.rack_box --data /work/data/realC [--split holdout]
        [--project datasets/real-photos] [--arm NAME=WEIGHTS ...] [--keep DIR]

`--data` is an export of the labelled photos (`annotate export`). The script writes a copy of it
whose images are cropped as `--rack-box` crops a photo when given the labels' rack (the bounding
box of the annotation's four corners, `racklay.predict.rack_crop` at the first arm's input aspect;
layouts, meta and splits are the export's own), then prints `bench.accuracy.structure_ab`'s table
for the whole photos and for the crops, arm by arm. The labels' box is tight; a user's box drawn
by hand is rougher, so the crops' row is an upper bound on what `--rack-box` gives. Asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.common import REPO


def cropped_copy(data: Path, project: Path, out: Path, aspect: float, split: str, jitter: float = 0.0,
                 seed: int = 0) -> list[float]:
    """`out` = `data` with the images of `split` cropped to their labelled rack (symlinks for the
    layouts, meta and splits); returns each crop's share of its photo's area. jitter: each edge of
    the labels' box moved by a uniform random share of the box's width (x) or height (y) in
    [-jitter, jitter], seeded: a box drawn by hand."""
    import numpy as np

    from racklay.atomic import atomic_save_png
    from racklay.data import RackLayRoot
    from racklay.predict import rack_crop

    src = RackLayRoot(data)
    out.mkdir(parents=True)
    for d in ("topLayouts", "frontLayouts", "meta", "splits"):
        os.symlink((data / d).resolve(), out / d)
    crops = []
    rng = np.random.default_rng(seed)
    for sid in src.split_ids(split):
        meta = src.read_meta(sid)
        name = meta.get("source_image")
        if not name:
            raise SystemExit(f"{src.meta_path(sid)}: no source_image (not an `annotate export`?)")
        ann_path = project / "annotations" / f"{name}.json"
        ann = json.loads(ann_path.read_text())
        image = src.read_image(sid)
        corners = np.asarray(ann["rack"]["corners"], float)
        corners *= [image.shape[1] / ann["image_size"][0], image.shape[0] / ann["image_size"][1]]
        box = np.array([*corners.min(0), *corners.max(0)])
        size = np.tile(box[2:] - box[:2], 2)
        box += rng.uniform(-jitter, jitter, 4) * size
        c = rack_crop(box, image.shape[1], image.shape[0], aspect, source=str(ann_path))
        atomic_save_png(out / "Images" / f"{sid}.png", image[c[1]:c[3], c[0]:c[2]])
        crops.append((c[2] - c[0]) * (c[3] - c[1]) / (image.shape[0] * image.shape[1]))
    return crops


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, type=Path, help="an `annotate export` of the labelled photos")
    ap.add_argument("--split", default="holdout", help="the split to score (default holdout)")
    ap.add_argument("--project", type=Path, default=REPO / "datasets" / "real-photos",
                    help="the annotate project the export came from (its annotations hold the racks' corners)")
    ap.add_argument("--arm", action="append", default=None, metavar="NAME=WEIGHTS",
                    help="a model to score (repeatable; default: the shipped one)")
    ap.add_argument("--jitter", type=float, default=0.0, metavar="F",
                    help="move each edge of the labels' box by up to F of its width or height (uniform, "
                         "seeded): a box drawn by hand (default 0: the labels' tight box)")
    ap.add_argument("--seed", type=int, default=0, help="seed of --jitter")
    ap.add_argument("--keep", type=Path, default=None, help="write the cropped copy here and keep it")
    args = ap.parse_args(argv)

    from racklay.checkpoint import load_checkpoint
    from racklay.release import resolve_weights

    arms = args.arm or [f"shipped={resolve_weights(None)}"]
    h, w = load_checkpoint(arms[0].split("=", 1)[1]).cfg.image_size
    with tempfile.TemporaryDirectory(prefix="rack_box_") as tmp:
        crop_root = args.keep or Path(tmp) / "crops"
        areas = sorted(cropped_copy(args.data, args.project, crop_root, w / h, args.split, args.jitter, args.seed))
        rough = f", each edge moved by up to {args.jitter:g} of the box's size (seed {args.seed})" if args.jitter else ""
        print(f"{len(areas)} {args.split} photos cropped to their labelled rack at the input's aspect {w}:{h}{rough} "
              f"(crop / photo area: median {areas[len(areas) // 2]:.2f}, min {areas[0]:.2f})\n", flush=True)
        for what, root in (("whole photos", args.data), ("cropped to the labelled rack", crop_root)):
            print(f"## {what}", flush=True)
            cmd = [sys.executable, "-m", "bench.accuracy.structure_ab", "--data", str(root), "--split", args.split]
            for a in arms:
                cmd += ["--arm", a]
            rc = subprocess.call(cmd, cwd=REPO)
            if rc:
                return rc
    return 0


if __name__ == "__main__":
    sys.exit(main())
