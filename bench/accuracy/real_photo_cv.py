"""Does fine-tuning on labelled real photos help on photos from *other* sources? Grouped cross-validation.

  .venv/bin/python -m bench.accuracy.real_photo_cv --weights MODEL --replay /data/release [--soup 0.3,0.5]

The labelled photos of an `annotate` project (default `datasets/real-photos/`) are grouped by
where they come from (`--group-by`, a column of the project's SOURCES.tsv: `site` by default, one
site and camera per group; `repo` gives the coarser grouping of the earlier runs). For each group, the model (`--weights`; it must not have seen these photos,
so not the shipped model, which was fine-tuned on them: the bench refuses it) is fine-tuned on the
photos of every *other* group, with synthetic replay (`--replay`: a rendered set's train split,
`--replay-ratio` renders per photo and epoch) and the model's own augmentation and loss (from
its metadata), and scored on the held-out group at the photos' own resolution. The table compares the model before
and after, per group and pooled over all photos (dataset-level IoU: every photo is scored by a
model that never saw its source). This is the honest estimate of what a fine-tune on labelled
photos buys on a new site; it asserts nothing. `--soup` also scores each fold's fine-tune
averaged with the start model (no training); `--onto MODEL` also scores each fold's fine-tune
*grafted* onto MODEL, a model trained further on renders from the same start: MODEL + a x
(fine-tune - start) for each `--soup` weight a (racklay.release.graft_update; no training). About
6 minutes per group on 2 CPU cores.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import REPO


def source_column(project: Path, column: str = "site") -> dict[str, str]:
    """photo file name -> its `column` (site, repo, video, ...) in the project's SOURCES.tsv."""
    src = project / "SOURCES.tsv"
    if not src.is_file():
        raise SystemExit(f"{src}: not found (the bench groups photos by their source)")
    with open(src, newline="") as f:
        reader = csv.DictReader(f, delimiter="\t")
        if column not in (reader.fieldnames or []):
            raise SystemExit(f"{src}: no {column!r} column to group by (columns: {', '.join(reader.fieldnames or [])})")
        return {r["file"]: r[column] for r in reader}


def photo_groups(project: Path, source_of: dict[str, str], column: str = "site") -> dict[str, list[str]]:
    """group (the SOURCES.tsv `column`) -> exported sample ids (`source_of`: sample id -> photo
    file name), from the project's SOURCES.tsv."""
    src = project / "SOURCES.tsv"
    repo_of = source_column(project, column)
    groups: dict[str, list[str]] = {}
    for sid, name in source_of.items():
        if name not in repo_of:
            raise SystemExit(f"{src}: no row for {name!r} (sample {sid})")
        groups.setdefault(repo_of[name], []).append(sid)
    return groups


def fold_root(export: Path, out: Path, train: list[str], test: list[str]) -> Path:
    """A RackLay root of links to the exported files with this fold's splits (val = the training
    photos: the curves only; the schedule is fixed and the last weights are scored)."""
    from racklay.data import RackLayRoot

    src, dst = RackLayRoot(export), RackLayRoot(out)
    for sid in train + test:
        for p in (src.image_path(sid), src.layout_path("top", sid), src.layout_path("front", sid),
                  src.meta_path(sid)):
            q = out / p.relative_to(export)
            q.parent.mkdir(parents=True, exist_ok=True)
            if not q.exists():
                os.symlink(p, q)
    dst.write_split("train", train)
    dst.write_split("val", train)
    dst.write_split("test", test)
    return out


def ious(results: list[dict]) -> dict[str, float]:
    """Dataset-level shelf / box IoU (%) per view over the pooled confusion matrices."""
    from racklay.metrics import confusion_scores

    out = {}
    for v in ("top", "front"):
        scores = confusion_scores(sum(np.array(r[v]["confusion"]) for r in results))
        for name in ("shelf", "box"):
            out[f"{v} {name}"] = 100 * scores[name]["IoU"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--project", type=Path, default=REPO / "datasets" / "real-photos",
                    help="annotate project of labelled photos with a SOURCES.tsv (default datasets/real-photos)")
    ap.add_argument("--group-by", default="site",
                    help="SOURCES.tsv column whose values are the cross-validation groups (default site; "
                         "repo: by source repository)")
    ap.add_argument("--weights", default=None, help="model to fine-tune (default: the shipped one)")
    ap.add_argument("--replay", type=Path, required=True,
                    help="synthetic RackLay root mixed into every epoch (its train split), e.g. the set the model "
                         "was trained on (docs/model-card.md has the shipped model's command)")
    ap.add_argument("--replay-ratio", type=float, default=1.0, help="renders per photo and epoch (default 1)")
    ap.add_argument("--epochs", type=int, default=100, help="epochs per fold (default 100)")
    ap.add_argument("--lr", type=float, default=2e-4, help="peak learning rate (default 2e-4)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--soup", default="", help="also score each fold's fine-tune averaged with the start model at "
                    "these weights of the fine-tune, e.g. 0.3,0.5 (racklay.release.average_checkpoints; no training)")
    ap.add_argument("--onto", default=None, help="also score MODEL + a x (fold fine-tune - start) for each --soup "
                    "weight a: the fine-tune's change grafted onto MODEL, a model trained on from the same start "
                    "(racklay.release.graft_update); MODEL must not have seen the photos either")
    ap.add_argument("--out", type=Path, default=None, help="keep the fold runs here (default: a temporary folder)")
    ap.add_argument("--json", default=None, help="also write the numbers here")
    args = ap.parse_args()

    from annotate.cli import main as annotate_main
    from racklay.checkpoint import load_checkpoint
    from racklay.data import RackLayRoot
    from racklay.evaluate import evaluate
    from racklay.predict import Predictor
    from racklay.release import average_checkpoints, graft_update, resolve_weights
    from racklay.train import TrainConfig, train
    from transfer.workflow import checkpoint_config, checkpoint_loss

    weights = Path(resolve_weights(args.weights)).resolve()
    mcfg = checkpoint_config(weights)
    tmp = tempfile.TemporaryDirectory(prefix="racklay-realcv-")
    work = args.out or Path(tmp.name)
    export = work / "export"
    if not (export / "splits" / "test.txt").is_file():
        if annotate_main(["export", str(args.project), "--out", str(export), "--split-fractions", "test=1"]) != 0:
            raise SystemExit(f"{args.project}: annotate export failed")
    root = RackLayRoot(export)
    source_of = {sid: (root.read_meta(sid) or {}).get("source_image") for sid in root.ids()}
    groups = photo_groups(args.project, source_of, args.group_by)
    onto = Path(args.onto).resolve() if args.onto else None
    metas = {model: load_checkpoint(model).meta for model in (weights, onto) if model is not None}
    for model, meta in metas.items():
        seen = set(meta.get("fine_tuned_on_photos", [])) & set(source_of.values())
        if seen:
            raise SystemExit(f"{model}: was fine-tuned on {len(seen)} of these photos, so a cross-validation on "
                             "them would be in-sample; pass a model that has not seen them (the model it "
                             f"was fine-tuned from: {meta.get('fine_tuned_from', 'see docs/model-card.md')})")
    # the model's own augmentation (the release recipe's `strong` for files that do not record it)
    augment = (metas[weights].get("train_config") or {}).get("augment") or "strong"
    print(f"model {weights}; {sum(map(len, groups.values()))} photos in {len(groups)} source groups: "
          + ", ".join(f"{g} {len(v)}" for g, v in groups.items()), flush=True)
    alphas = [float(a) for a in args.soup.split(",") if a.strip()]
    if any(not 0 < a < 1 for a in alphas):
        raise SystemExit(f"--soup: weights must be in (0, 1), got {args.soup}")
    if onto is not None and not alphas:
        raise SystemExit("--onto needs --soup: the weights a of the grafted fine-tune")
    # the start model and the graft base are the same in every fold: load each once
    start_pred = Predictor(str(weights))
    onto_pred = Predictor(str(onto)) if onto is not None else None
    before, after, rows = [], [], []
    soups: dict[float, list] = {a: [] for a in alphas}
    onto_before: list = []
    grafts: dict[float, list] = {a: [] for a in alphas}
    for g, test in groups.items():
        train_ids = [s for h, v in groups.items() if h != g for s in v]
        root = fold_root(export, work / f"fold-{g.replace('/', '_')}", train_ids, test)
        t0 = time.time()
        cfg = TrainConfig(data=str(root), out=str(work / "runs"), name=g.replace("/", "_"), init=str(weights),
                          epochs=args.epochs, lr=args.lr, warmup_steps=20, image_size=mcfg.image_size,
                          layout_size=mcfg.layout_size, R=mcfg.R, views=tuple(mcfg.views), decoder=mcfg.decoder,
                          encoder=mcfg.encoder, letterbox=mcfg.letterbox, disc=mcfg.disc, augment=augment,
                          replay=str(args.replay), replay_ratio=args.replay_ratio, seed=args.seed, patience=None,
                          checkpoint_every=0, progress=False, **checkpoint_loss(weights))
        cfg.resume = (cfg.run_dir() / "last.safetensors").is_file()   # --out kept: continue / reuse
        run = train(cfg)
        r0 = evaluate(start_pred, root, split="test", native=True, progress=False)
        r1 = evaluate(str(run / "last.safetensors"), root, split="test", native=True, progress=False)
        before.append(r0)
        after.append(r1)
        for a in alphas:
            soup = average_checkpoints([weights, run / "last.safetensors"], run / f"soup-{a:g}.safetensors",
                                       weights=[1 - a, a])
            soups[a].append(evaluate(str(soup), root, split="test", native=True, progress=False))
        if onto is not None:
            onto_before.append(evaluate(onto_pred, root, split="test", native=True, progress=False))
            for a in alphas:
                g_path = graft_update(onto, weights, run / "last.safetensors", run / f"graft-{a:g}.safetensors", a)
                grafts[a].append(evaluate(str(g_path), root, split="test", native=True, progress=False))
        rows.append((g, len(test), ious([r0]), ious([r1])))
        print(f"fold {g}: trained on {len(train_ids)} photos, {(time.time() - t0) / 60:.1f} min", flush=True)
    n_all = sum(len(v) for v in groups.values())
    rows.append(("pooled (all photos)", n_all, ious(before), ious(after)))
    for a in alphas:
        rows.append((f"pooled, start + {a:g} x (fine-tune - start)", n_all, ious(before), ious(soups[a])))
    for a in alphas if onto is not None else ():
        rows.append((f"pooled, onto + {a:g} x (fine-tune - start)", n_all, ious(onto_before), ious(grafts[a])))
    keys = list(rows[0][2])
    print(f"\n{'held-out source':44s} {'n':>3s}  " + "  ".join(f"{k:>19s}" for k in keys))
    for g, n, a, b in rows:
        print(f"{g:44s} {n:3d}  " + "  ".join(f"{a[k]:6.1f} -> {b[k]:5.1f} ({b[k] - a[k]:+5.1f})" for k in keys))
    print("(dataset-level IoU %, start model -> fine-tuned on the other sources' photos"
          + (f"; onto rows: {onto} -> with the fold's fine-tune grafted)" if onto is not None else ")"))
    if args.json:
        Path(args.json).write_text(json.dumps({"weights": str(weights), "onto": str(onto) if onto else None, "args": {k: str(v) for k, v in vars(args).items()},
                                               "rows": [{"group": g, "n": n, "before": a, "after": b}
                                                        for g, n, a, b in rows]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
