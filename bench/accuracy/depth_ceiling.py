"""How much of the top view's box IoU a model can reach without seeing how deep the boxes are.

    .venv/bin/python -m bench.accuracy.depth_ceiling --data /work/data/complex8k [--split val] [--n 400]

Reads only the truth (the top-view layouts of N images spread over the split) and scores oracles
that know everything the front of the rack shows, and guess the depth:
- presence known, front edge known: in every layout column that holds a box, the box's true
  front edge (its row nearest the camera), then a constant depth, the best of a sweep; and
  a depth that is a constant fraction of the shelf behind the front edge;
- presence known, front edge not known: the box drawn from the shelf's front edge (no set-back),
  the best constant depth; and the box centred on the shelf's depth (the paper authors' placement,
  recipe `complex_paper`), the best constant depth.
A model that reads presence and front edges perfectly but cannot see depth scores at most about
these numbers on the split (dataset-level box IoU, the metric of the issue's ">= 70" top-view
target and of the paper-protocol box cell). On WareSynth renders a box's depth is its category's
size with a relative jitter (`size_jitter`), turned on a quarter of the slots, set back from the
front edge at random and sometimes followed by a second box behind it: none of which a camera
about level with the shelf sees well. Prints numbers; asserts nothing.
"""
from __future__ import annotations

import argparse

import numpy as np

from racklay.data import RackLayRoot


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="RackLay dataset root (renders: truth only is read)")
    ap.add_argument("--split", default="val")
    ap.add_argument("--n", type=int, default=400, help="images, spread evenly over the split (default 400)")
    args = ap.parse_args(argv)

    root = RackLayRoot(args.data)
    ids = root.split_ids(args.split)
    if not ids:
        raise SystemExit(f"{args.data}: split {args.split!r} is empty")
    ids = [ids[i] for i in np.linspace(0, len(ids) - 1, min(args.n, len(ids))).astype(int)]
    T = np.stack([root.read_layouts("top", s) for s in ids])      # (N, R, D, D): rows depth, front at the bottom
    box, foot = T == 2, T > 0
    D = T.shape[-1]
    rows = np.arange(D)[None, None, :, None]
    has = box.any(2)[:, :, None, :]                                 # columns holding a box
    front = np.where(box, rows, -1).max(2)[:, :, None, :]           # the box's front edge: its row nearest the camera
    shelf_front = np.where(foot, rows, -1).max(2)[:, :, None, :]
    shelf_back = np.where(foot, rows, D).min(2)[:, :, None, :]
    print(f"{args.data} [{args.split}]: {len(ids)} images, {int(box.sum())} true top-view box pixels, D = {D}")

    def sweep(band):
        """The best constant depth k (rows) for boxes in every box column, band(k) their rows."""
        return max((iou(has & band(k), box), k) for k in range(1, D // 4))

    def behind(edge):
        return lambda k: (rows <= edge) & (rows > edge - k)

    best, k = sweep(behind(front))
    print(f"presence and front edge known, constant depth: box IoU {100 * best:.1f} (best depth {k} rows)")
    for f in (0.5, 0.7, 1.0):
        kk = np.maximum(1, np.round(f * (front - shelf_back + 1)))
        print(f"presence and front edge known, depth {f:.0%} of the shelf behind it: box IoU "
              f"{100 * iou(has & (rows <= front) & (rows > front - kk), box):.1f}")
    best, k = sweep(behind(shelf_front))
    print(f"presence known, drawn from the shelf's front edge, constant depth: box IoU {100 * best:.1f} (best depth {k} rows)")
    # centred on the shelf's depth (the placement of the paper authors' WareSynth, recipe complex_paper)
    mid2 = shelf_front + shelf_back                                  # twice the shelf's centre row
    best, k = sweep(lambda k: (2 * rows <= mid2 + k) & (2 * rows > mid2 - k))
    print(f"presence known, centred on the shelf's depth, constant depth: box IoU {100 * best:.1f} (best depth {k} rows)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
