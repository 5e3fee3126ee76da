"""Where a model's layout error is: metric size of the shelf footprint, box placement, shelf channels.

  .venv/bin/python -m bench.accuracy.error_analysis --weights W --data ROOT [--split val] [--n 240]

Per view, on N images spread over the split: dataset-level shelf / box / footprint (shelf + box)
IoU; box IoU inside the true footprint and the box-vs-shelf accuracy there; visible-shelf
channels in truth and prediction; per shelf channel, the footprint IoU before and after the x / y
rescale about the map centre (0.6-1.6) that fits the truth best, the median best scale, and box
IoU after applying that scale. Top view: where the box error lies in depth, as shares of the true
box pixels missed (FN) and drawn wrongly (FP) in columns where truth and prediction disagree on
whether a box stands, in columns with one box in depth and in columns with a box behind another
(where a one-interval structure must hedge; `--struct-back`), and on renders the top-view box
IoU and those two depth errors by the camera's height above each shelf's board.
docs/results/2026-11-22-to-26-accuracy-log.md ("Where the error is") was measured with it.
Prints numbers; asserts nothing.
"""
import argparse

import numpy as np
import torch
import torch.nn.functional as F

from racklay.checkpoint import load_model
from racklay.predict import decide
from racklay.release import resolve_weights
from racklay.torchdata import RackLayDataset

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("--weights", default=None, help="model (default: the shipped one)")
ap.add_argument("--data", required=True, help="RackLay dataset root")
ap.add_argument("--split", default="val")
ap.add_argument("--n", type=int, default=240, help="images, spread evenly over the split")
ap.add_argument("--threads", type=int, default=2)
args = ap.parse_args()
torch.set_num_threads(args.threads)
w, data, split, n = str(resolve_weights(args.weights)), args.data, args.split, args.n
model, cfg, _ = load_model(w); model.eval()
ds = RackLayDataset(data, split, cfg.image_size, cfg.layout_size, cfg.views, R=cfg.R, letterbox=cfg.letterbox)
idx = np.linspace(0, len(ds) - 1, n).astype(int)
P = {v: [] for v in cfg.views}; G = {v: [] for v in cfg.views}
with torch.no_grad():
    for s in range(0, n, 8):
        items = [ds[i] for i in idx[s:s + 8]]
        out = model(torch.stack([it["image"] for it in items]))
        for v in cfg.views:
            # the model's decision as `racklay predict` makes it (numpy's argmax: torch's over the class
            # axis is ~10x slower on CPU), with its calibrated bias if it carries one
            bias = (cfg.decision_bias or {}).get(v)
            P[v].append(torch.from_numpy(decide(out[v].float().numpy(), bias)).long())
            G[v].append(torch.stack([it[v] for it in items]))
scales = torch.tensor([0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.2, 1.3, 1.4, 1.6])
def iou(a, b): return (a & b).sum().item() / max((a | b).sum().item(), 1)
for v in cfg.views:
    p, g = torch.cat(P[v]), torch.cat(G[v])                       # (N, R, S, S)
    print(f"== {v}: {len(p)} images")
    print(f"  dataset-level shelf IoU {iou(p == 1, g == 1):.3f}  box IoU {iou(p == 2, g == 2):.3f}  "
          f"foreground (shelf+box) IoU {iou(p > 0, g > 0):.3f}")
    gm = g > 0
    print(f"  box IoU inside the true footprint {iou((p == 2) & gm, g == 2):.3f}; "
          f"box vs shelf split inside true footprint: acc {((p[gm] == 2) == (g[gm] == 2)).float().mean():.3f}")
    # channels: visible shelves
    gv = (g > 0).flatten(2).float().mean(2) > 0.002; pv = (p > 0).flatten(2).float().mean(2) > 0.002
    print(f"  visible-shelf channels: GT {gv.sum().item()}, pred {pv.sum().item()}, both {(gv & pv).sum().item()}; "
          f"images with the same count {(gv.sum(1) == pv.sum(1)).float().mean():.3f}")
    # oracle anisotropic scale of the predicted footprint about the map centre (64x64)
    fp = F.interpolate((p > 0).float().flatten(0, 1)[:, None], size=128, mode="nearest")
    fg = F.interpolate((g > 0).float().flatten(0, 1)[:, None], size=128, mode="nearest")
    bp = F.interpolate((p == 2).float().flatten(0, 1)[:, None], size=128, mode="nearest")
    bg = F.interpolate((g == 2).float().flatten(0, 1)[:, None], size=128, mode="nearest")
    keep = (fg.flatten(1).sum(1) > 0) & (fp.flatten(1).sum(1) > 0)
    fp, fg, bp, bg = fp[keep], fg[keep], bp[keep], bg[keep]
    base = ((fp * fg).flatten(1).sum(1) / ((fp + fg) > 0).float().flatten(1).sum(1))
    best = base.clone(); bsx = torch.ones_like(base); bsy = torch.ones_like(base)
    for sx in scales:
        for sy in scales:
            th = torch.tensor([[1 / sx, 0, 0], [0, 1 / sy, 0]], dtype=torch.float32).expand(len(fp), 2, 3)
            grid = F.affine_grid(th, fp.shape, align_corners=False)
            q = F.grid_sample(fp, grid, mode="nearest", align_corners=False)
            i_ = ((q * fg).flatten(1).sum(1) / ((q + fg) > 0).float().flatten(1).sum(1))
            better = i_ > best
            best = torch.where(better, i_, best); bsx = torch.where(better, sx, bsx); bsy = torch.where(better, sy, bsy)
    th = torch.stack([torch.stack([1 / bsx, 0 * bsx, 0 * bsx], 1), torch.stack([0 * bsy, 1 / bsy, 0 * bsy], 1)], 1)
    q = F.grid_sample(bp, F.affine_grid(th, bp.shape, align_corners=False), mode="nearest", align_corners=False)
    print(f"  box IoU (these channels, 128 px): {iou(bp > 0, bg > 0):.3f}; after the footprint's best scale "
          f"{iou(q > 0, bg > 0):.3f}")
    qs = torch.quantile(torch.stack([bsx, bsy]), torch.tensor([0.1, 0.25, 0.5, 0.75, 0.9]), dim=1)
    print(f"  best-scale quantiles 10/25/50/75/90 %: x {[round(v, 2) for v in qs[:, 0].tolist()]} "
          f"y {[round(v, 2) for v in qs[:, 1].tolist()]}")
    print(f"  per-channel footprint IoU (both non-empty, {len(base)}): mean {base.mean():.3f}; with the best "
          f"x/y scale {best.mean():.3f}; median best scale x {bsx.median():.2f} y {bsy.median():.2f}; "
          f"|log s| > 0.1 in {((bsx.log().abs() > 0.1) | (bsy.log().abs() > 0.1)).float().mean():.2f}")
    if v == "top":                                                 # rows are depth, columns run along the shelf
        pb, gb = p == 2, g == 2
        runs = (gb & ~F.pad(gb, (0, 0, 1, 0))[..., :-1, :]).sum(2)  # (N, R, S) separate box runs per column
        agree = pb.any(2) & gb.any(2)
        fn, fp, total = gb & ~pb, pb & ~gb, max(gb.sum().item(), 1)
        parts = (("presence disagrees", ~agree), ("one box in depth", agree & (runs == 1)),
                 ("a box behind another", agree & (runs >= 2)))
        print(f"  box error in depth (shares of the {total} true box pixels; columns with a box behind another: "
              f"{(runs >= 2).sum().item()} of {(runs >= 1).sum().item()}):")
        for name, cols in parts:
            m = cols.unsqueeze(2)
            print(f"    {name:<22} FN {(fn & m).sum().item() / total:.3f}  FP {(fp & m).sum().item() / total:.3f}")
        # the same by where the camera is: its height above each shelf's board (renders' meta). From
        # below a board the tops of its boxes are hidden; from above, their depth is in view.
        metas = [ds.root.read_meta(ds.ids[i]) or {} for i in idx]
        if all("camera" in m and "shelf_board_tops" in m for m in metas):
            above = torch.full(gb.shape[:2], float("nan"))
            for j, m in enumerate(metas):
                tops = m["shelf_board_tops"][:cfg.R]
                above[j, :len(tops)] = m["camera"]["position_world"][2] - torch.tensor(tops, dtype=torch.float32)
            print("  top-view box IoU by the camera's height above the shelf's board (shelf channels with a true box):")
            has = gb.flatten(2).any(2)
            for rng, lo, hi in (("below", -99, 0.0), ("0-0.5 m", 0.0, 0.5), ("0.5-1 m", 0.5, 1.0),
                                ("1-2 m", 1.0, 2.0), ("2 m +", 2.0, 99)):
                sel = has & (above >= lo) & (above < hi)
                if sel.any():
                    s_ = sel[..., None, None]
                    single = (fp & s_ & (agree & (runs == 1)).unsqueeze(2)).sum().item()
                    behind = (fn & s_ & (agree & (runs >= 2)).unsqueeze(2)).sum().item()
                    tb = max((gb & s_).sum().item(), 1)
                    print(f"    {rng:<10} {sel.sum().item():>4} channels  box IoU {iou(pb & s_, gb & s_):.3f}  "
                          f"too deep behind single boxes {single / tb:.3f}  back boxes missed {behind / tb:.3f}")
