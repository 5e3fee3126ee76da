"""Where a struct model's gap signal is lost on labelled photos: in detecting the gaps, or in
placing the shelf in the image.

    .venv/bin/python -m bench.accuracy.gap_signal --data /tmp/real131 --split test [--weights W]
        [--project datasets/real-photos] [--signal gap|gap_main|gap_cue]

`--data` is a RackLay dataset exported from an annotate project (`annotate export`: each sample's
meta names its source photo) and `--project` that project, whose annotations give each photo's
rack homography. Over the front-view shelves whose labels hold two or more box runs (boxes less
than 2 cm apart merged, as the layouts draw them), it prints the rank AUC of gap against box for:

- **per position** (as `structure_ab.py` scores it): the gap output at position t against the
  label's position t, both sampled along their own shelf length. A model that places the shelf
  in the wrong part of the image scores low here even when it sees every gap.
- **in the image**: each of the model's positions labelled by what the photo's label has at the
  image column that position reads (`racklay.model.position_columns`, mapped onto the label's
  rack through its homography at 30 % of the level's clear height): gap, box, or neither (left
  out). Placement-free: a model whose gap output responds to the photo's gaps scores high
  however it places the shelf.
- **the darkness cue at the model's positions**: one minus the luminance at each position (the
  input pooled over image rows with the model's own row attention for that shelf) over the
  shelf's median: what a trivial image cue scores with the model's rows and columns.
- **the darkness cue at the labelled geometry**: the same cue every 1 cm along the labelled
  shelf, over the rows from the board to 60 % of the clear height: the cue without the model.

and how far the model's shelf ends lie from the labelled rack's ends in the image (median
absolute error, image widths). Numbers only; nothing is asserted.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.accuracy.structure_ab import rank_auc
from bench.accuracy.synth_coverage import run_spans
from racklay.data import luminance
from racklay.predict import add_precision_args

#: the darkness cue at the labelled geometry pools the rows from the board to this share
CUE_ROWS = (0.05, 0.6)


def model_darkness(lum, att_logits, cols):
    """Relative darkness (R, T) at the model's positions: the luminance (H, W) pooled over rows
    with the row attention (R, h, w) upsampled to it, read at image columns `cols` (R, T, image
    widths), one minus its ratio to the shelf's median."""
    import torch.nn.functional as F

    H, W = lum.shape
    att = F.interpolate(att_logits[None].float(), size=(H, W), mode="bilinear", align_corners=False)[0].softmax(1)
    prof = (att * lum).sum(1).numpy()                                            # (R, W)
    x = np.clip(cols * W - 0.5, 0, W - 1)
    val = np.stack([np.interp(x[r], np.arange(W), prof[r]) for r in range(len(prof))])
    return 1 - val / np.maximum(np.median(val, -1, keepdims=True), 1e-3)


def shelf_runs(scene, r: int):
    """The box runs (u0, u1) on shelf r of a labelled scene, and the gaps between them."""
    runs = run_spans([(b.u0, b.u1) for b in scene.boxes if b.shelf == r])
    return runs, [(runs[k][1], runs[k + 1][0]) for k in range(len(runs) - 1)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, type=Path, help="RackLay dataset exported from the project")
    ap.add_argument("--split", default="test", help="split of --data to score (default test)")
    ap.add_argument("--project", default=Path("datasets/real-photos"), type=Path,
                    help="the annotate project the dataset was exported from (default datasets/real-photos)")
    ap.add_argument("--weights", default=None, help="a struct checkpoint with a gap output (default: the shipped model)")
    ap.add_argument("--signal", default="gap", choices=("gap", "gap_main", "gap_cue"),
                    help="the model's gap logit to score: the one drawn (default), or with --struct-cue either "
                         "detector alone (gap_main: the features', gap_cue: the brightness cue's)")
    add_precision_args(ap)
    args = ap.parse_args(argv)

    from annotate import geometry as G
    from annotate.schema import pixel_aspect
    from annotate.store import Project
    from racklay.data import SPAN_AT_CLEAR_HEIGHT
    from racklay.evaluate import split_dataset
    from racklay.model import position_columns
    from racklay.predict import Predictor
    from racklay.release import resolve_weights
    from racklay.structure import gap_positions, truth_structure
    from racklay.torchdata import batch_luminance, data_loader

    pred = Predictor(str(resolve_weights(args.weights)), precision=args.precision)
    if pred.model is None or pred.cfg.decoder != "struct" or not pred.cfg.struct_gap or "front" not in pred.views:
        ap.error(f"{pred.weights}: needs a struct model with a gap output and a front view")
    if args.signal != "gap" and not pred.cfg.struct_cue:
        ap.error(f"{pred.weights}: --signal {args.signal} needs a model with the brightness cue (--struct-cue)")
    project = Project(args.project, create=False)
    dec = pred.model.trunk_decoder("front")   # the decoder whose row attention reads the front view
    cap = {}
    hooks = [dec.row_att.register_forward_hook(lambda m, i, o: cap.__setitem__("att", o.detach()))]
    _, _, ds = split_dataset(pred, args.data, args.split)
    arms = ("per position", "in the image", "darkness cue, model's positions", "darkness cue, labelled geometry")
    pooled = {k: ([], []) for k in arms}
    per_shelf = {k: [] for k in arms}
    ends = []

    def add(arm, score, is_gap, is_box):
        ok = np.isfinite(score)
        g, b = score[is_gap & ok], score[is_box & ok]
        if len(g) and len(b):
            pooled[arm][0].append(g)
            pooled[arm][1].append(b)
            per_shelf[arm].append(rank_auc(g, b))

    loader = data_loader(ds, 0, batch_size=1, shuffle=False)
    for sid, batch in zip(ds.ids, loader):
        meta = ds.root.read_meta(sid) or {}
        if meta.get("source") != "annotate":
            raise SystemExit(f"{ds.root.meta_path(sid)}: not exported from an annotate project (no source photo)")
        ann = project.load(meta["source_image"])
        scene = G.build_scene(ann, project.settings)
        W, H = ann["image_size"]
        st = pred.structures(batch["image"])["front"]
        gap = st[args.signal][0].float().numpy()
        T = gap.shape[-1]
        cols = position_columns(st["centre"][0], st["half"][0], T).numpy()         # (R, T)
        dark = model_darkness(batch_luminance(batch["image"])[0, 0], cap["att"][0], cols)
        truth = truth_structure("front", batch["front"].long(), pred.grid.extent, T)
        tgap = (gap_positions(truth["box"]) & truth["presence"].unsqueeze(-1))[0].numpy()
        tbox = truth["box"][0].numpy()
        for r in np.nonzero(tgap.any(-1))[0]:
            add("per position", gap[r], tgap[r], tbox[r])
        photo = None
        for r in range(min(len(scene.shelf_v), len(gap))):
            runs, gaps = shelf_runs(scene, r)
            if len(runs) < 2:
                continue
            v0, clear = scene.shelf_v[r], scene.clear[r]

            def to_x(us):
                """Image x (image widths) of rack positions `us` (metres) at the label's row."""
                us = np.asarray(us, np.float64).ravel()
                return scene.plane.to_image(np.c_[us, np.full(len(us), v0 + SPAN_AT_CLEAR_HEIGHT * clear)])[:, 0] / W

            def inside(xs, spans):
                ends_x = to_x(np.ravel(spans)).reshape(-1, 2)
                lo, hi = ends_x.min(1), ends_x.max(1)
                return ((xs[:, None] >= lo) & (xs[:, None] <= hi)).any(1)

            is_gap = inside(cols[r], gaps)
            is_box = inside(cols[r], runs) & ~is_gap
            add("in the image", gap[r], is_gap, is_box)
            add("darkness cue, model's positions", dark[r], is_gap, is_box)
            left, right = scene.level_spans(W)[r]
            ends.append((abs(cols[r][0] - left), abs(cols[r][-1] - right)))
            # the cue at the labelled geometry, every 1 cm along the shelf
            if photo is None:      # as the labeller saw it: a squeezed photo at its aspect as taken
                rgb = G.restore_aspect(project.read_image(meta["source_image"]), pixel_aspect(project.settings))
                if rgb.shape[:2] != (H, W):
                    raise SystemExit(f"{project.annotation_path(meta['source_image'])}: labelled on a "
                                     f"{W}x{H} photo, the photo is {rgb.shape[1]}x{rgb.shape[0]}")
                photo = luminance(rgb) / 255.0
            us, val = G.plane_profile(photo, scene.plane, runs[0][0], runs[-1][1], v0, v0 + clear, CUE_ROWS)
            u_gap = np.array([any(a < u < b for a, b in gaps) for u in us])
            u_box = np.array([any(a <= u <= b for a, b in runs) for u in us]) & ~u_gap
            if np.isfinite(val).any():
                add("darkness cue, labelled geometry", 1 - val / max(float(np.nanmedian(val)), 1e-3), u_gap, u_box)
    for h in hooks:
        h.remove()
    print(f"\n{pred.weights.name} on {args.data}:{args.split} ({len(ds)} photos), front-view shelves whose labels hold "
          f">= 2 box runs; rank AUC of gap against box (0.5 = chance):\n")
    print("| signal | pooled AUC | median per shelf | shelves |\n|---|---|---|---|")
    for k in arms:
        p, n = pooled[k]
        auc = rank_auc(np.concatenate(p), np.concatenate(n)) if p else float("nan")
        med = float(np.median(per_shelf[k])) if per_shelf[k] else float("nan")
        print(f"| {k} | {auc:.3f} | {med:.3f} | {len(per_shelf[k])} |")
    if ends:
        e = np.array(ends)
        print(f"\nthe model's shelf ends against the labelled rack's, in the image: median |error| "
              f"{np.median(e[:, 0]):.2f} (left), {np.median(e[:, 1]):.2f} (right) image widths, over {len(e)} shelves")
    return 0


if __name__ == "__main__":
    sys.exit(main())
