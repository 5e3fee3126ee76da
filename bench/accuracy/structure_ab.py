"""Decoder A/B at equal CPU time: the structured model issue's numbers for each arm.

  .venv/bin/python -m bench.accuracy.structure_ab --arm light=/work/runs/ab-light --arm struct=/work/runs/ab-struct \\
      --data /work/data/complex [--split test] [--limit N] [--photos datasets/real-photos] [--calibrate-on DATA:SPLIT]

For every arm (a `racklay train` run folder: its best.safetensors, config.yaml and metrics.csv; or
a checkpoint file such as a release, which has no training cost to report; or several of them,
comma-separated: render draws or training seeds of one arm, each scored and the numbers averaged,
each run's box IoU listed under the tables — one draw and one seed of a renders-only arm are
readable only beyond ~10 box points on the photos, docs/accuracy.md) it prints, on the
held-out split of `--data` (WareSynth `complex` for the reproduction row):
- dataset-level shelf / box IoU (top / front) and the paper-protocol mIoU, metric and with
  `--scale-from-truth` (each predicted shelf scaled to its true length: shape alone);
- box AP (top / front): how well the arm's box probability ranks box pixels above the rest,
  whatever the threshold. On real photos a renders-only arm's box probabilities sit near 0.5, so
  its argmax box IoU can fall from ~45 to ~17 between two render draws of one recipe while its
  AP moves a few points (docs/results/2026-11-27-thirteenth-session.md): compare arms by both;
- with `--calibrate-on DATA:SPLIT` (e.g. the exported photos' `train` split: sites the held-out
  split does not show), each run's box IoU once more with decision biases fitted there (`racklay
  calibrate`): the score a renders-only recipe gives once its threshold is set on photos of
  other sites, which is what its photo step or a user's calibration would do;
- boxes as boxes: the front-view shelf channels whose truth has two or more separate runs of box
  columns along x, how many of them the arm also separates, how many with a gap where the truth
  has one ("placed": within 5 % of the shelf's length), and how many it separates at all;
- gap AUC (struct arms, torch): on those shelves, how well the arm's per-position signal ranks the
  truth's gap positions above its box positions (`gap_auc`: the gap output where the arm has one,
  else the box logit, negated; 0.5 is no skill), sampled along each true shelf as the structure
  loss is, so it reads the shape whatever the metric size. It needs no threshold: an arm that
  separates no shelf may still carry a signal a threshold or a photo step could use, or may not;
- time to accuracy: the run's CPU-minutes (wall minutes x threads x processes, as metrics.csv
  records them; `-` for a run recorded before it did, on the default threads) and CPU-minutes per
  point of validation score (mean of shelf and box IoU, x100);
- with `--photos` (an annotate project, e.g. the labelled real photos): metric and scale-from-truth
  IoU on them (out of domain: the arms were trained on renders only), and the photos whose labels
  show two or more separate boxes on a shelf (front view) and how many of them the arm shows so,
  and the photos whose labels hold two or more shelves and how many of them the arm finds all of
  (`racklay.metrics.shelf_counts`: a merged or missed level).
- for arms with a gap output (`--struct-gap`), the metric IoU and separation again with the gap
  cut off (`racklay eval --no-gap-cut`: boxes from the box output alone). A gap output trained on
  renders can over-cut photos, and how much varies from run to run: this column tells a look's
  effect on the layout from the gap output's calibration, which a photo step retrains.
Targets of the issue are printed beside the numbers (MET / NOT MET); nothing is asserted.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.common import PAPER_ROW
from bench.common import REPRODUCTION_BOX_TARGET as BOX_TARGET
from racklay.predict import add_precision_args


def separation(res: dict, unit: str = "shelves") -> dict | None:
    """An `evaluate` result's front-view separation counts (`racklay.metrics`: shelf channels whose
    truth holds >= 2 box runs; `unit` "images": an image counts when any of its shelves does, so
    for photos "does the prediction show separate boxes on the shelf where the photo does"), or
    None without a front view."""
    return res.get("front", {}).get("separation", {}).get(unit)


def sep_cell(c: dict | None) -> str:
    """The table cell "separated / truth; placed; predicted"."""
    return f"{c['separated']:g} / {c['truth']:g}; {c['placed']:g}; {c['predicted']:g}" if c else "-"


def centre_cut(root, split, limit, D: int | None, per_image: bool = False) -> int:
    """The chance line for "placed": front-view channels (`per_image`: images) whose truth, at
    D x D (None: as stored), has >= 2 box runs that one cut at the middle of every shelf would place
    (`racklay.layout.gaps_match` with a single gap at 0.5; two loads per bay are common)."""
    from racklay import layout as L
    from racklay.data import RackLayRoot

    data = RackLayRoot(root)
    n = 0
    for sid in data.resolve(split)[:limit]:
        front = data.read_layouts("front", sid)
        if D is not None:
            front = L.resize_layouts(front, D)
        hits = [L.gaps_match(L.box_gaps(ch), [(0.5, 0.5)]) for ch in front]   # one gap: two box runs
        n += any(hits) if per_image else sum(hits)
    return n


def rank_auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """P(a positive scores above a negative), ties counting half (the Mann-Whitney AUC)."""
    neg = np.sort(np.asarray(neg, np.float64).ravel())
    pos = np.asarray(pos, np.float64).ravel()
    if not len(pos) or not len(neg):
        return float("nan")
    below = np.searchsorted(neg, pos, "left")
    ties = np.searchsorted(neg, pos, "right") - below
    return float((below + 0.5 * ties).sum() / (len(pos) * len(neg)))


def gap_auc(pred, data, split: str, limit: int | None = None) -> dict | None:
    """How well a struct model's per-position signal ranks the truth's gaps between boxes above
    its boxes, on the front-view shelves whose truth has a gap (`racklay.structure.gap_positions`,
    sampled at the truth's own length, as `structure_loss` compares them): the gap output's logit
    where the model has one, else the drawn box logit negated. {"auc": pooled over positions,
    "median_shelf": the median of the per-shelf AUCs, "shelves": how many} or None (not a torch
    struct model, or no shelf with a gap)."""
    from racklay.evaluate import split_dataset
    from racklay.structure import gap_positions, truth_structure
    from racklay.torchdata import data_loader

    if pred.model is None or pred.cfg.decoder != "struct" or "front" not in pred.views:
        return None
    _, views, ds = split_dataset(pred, data, split, limit)
    if "front" not in views:
        return None
    pos, neg, per = [], [], []
    for batch in data_loader(ds, 0, batch_size=8, shuffle=False):
        st = pred.structures(batch["image"])["front"]
        score = (st["gap"] if "gap" in st else -st["box"]).float()
        tr = truth_structure("front", batch["front"].long(), pred.grid.extent, score.shape[-1])
        gaps = gap_positions(tr["box"]) & tr["presence"].unsqueeze(-1)
        for n, r in zip(*np.nonzero(gaps.any(-1).numpy())):
            s, g, b = score[n, r].numpy(), gaps[n, r].numpy(), tr["box"][n, r].numpy()
            pos.append(s[g])
            neg.append(s[b])
            per.append(rank_auc(s[g], s[b]))
    if not per:
        return None
    return {"auc": rank_auc(np.concatenate(pos), np.concatenate(neg)), "median_shelf": float(np.median(per)),
            "shelves": len(per)}


def gap_cell(g: dict | None) -> str:
    return f"{g['auc']:.2f} ({g['median_shelf']:.2f}; {g['shelves']:g})" if g else "-"


def run_cost(run: Path) -> tuple[float | None, float]:
    """(CPU-minutes of the run, None where its metrics.csv and config.yaml do not say how many
    threads trained it (`racklay.history.run_cpu_minutes`); best validation score x 100)."""
    from racklay.history import run_cpu_minutes

    if not (run / "config.yaml").is_file():
        raise SystemExit(f"{run}: no config.yaml (an arm is a `racklay train` run folder or a checkpoint file)")
    rows, cpu = run_cpu_minutes(run)
    best = max((r["val_score"] for r in rows if "val_score" in r), default=float("nan"))
    return cpu[-1], 100 * best


def scores(res: dict) -> dict:
    out = {}
    for v in ("top", "front"):
        if v in res:
            d = res[v]["dataset"]
            out[v] = {"shelf": 100 * d["shelf"]["IoU"], "box": 100 * d["box"]["IoU"],
                      "box_AP": 100 * d["box"].get("AP", float("nan")),
                      "rack_mIoU": 100 * res[v]["paper"]["rack"]["mIoU"], "box_mIoU": 100 * res[v]["paper"]["box"]["mIoU"]}
    return out


def fmt(s: dict) -> str:
    return " / ".join(f"{s[v]['shelf']:.1f}, {s[v]['box']:.1f}" for v in ("top", "front") if v in s)


def fmt_ap(s: dict) -> str:
    """Box AP (top / front): how well P(box) ranks box pixels above the rest, whatever the threshold."""
    return " / ".join(f"{s[v].get('box_AP', float('nan')):.1f}" for v in ("top", "front") if v in s)


def score_run(pred, run: Path, args, photos) -> dict:
    """One run's numbers (the keys of the JSON's arm rows)."""
    from racklay.evaluate import evaluate
    from racklay.metrics import shelves_found

    row = {"decoder": pred.cfg.decoder}
    res = evaluate(pred, args.data, split=args.split, limit=args.limit, progress=False)
    row["metric"], row["separation"] = scores(res), separation(res)
    row["gap_auc"] = gap_auc(pred, args.data, args.split, args.limit)
    row["shape"] = scores(evaluate(pred, args.data, split=args.split, limit=args.limit, progress=False,
                                   scale_from_truth=True))
    row["cpu_minutes"], row["best_val"] = run_cost(run) if run.is_dir() else (None, None)
    if args.calibrate_on:
        # the decision biases fitted on labelled photos of other sites, then the held-out split
        from dataclasses import replace

        from racklay.calibrate import calibrated_config, fit_decision_bias

        root, _, cal_split = args.calibrate_on.rpartition(":")
        own = pred.cfg
        pred.cfg = calibrated_config(replace(own, decision_bias=None),
                                     fit_decision_bias(pred, root, split=cal_split, progress=False))
        try:
            row["calibrated"] = scores(evaluate(pred, args.data, split=args.split, limit=args.limit, progress=False))
        finally:
            pred.cfg = own
    if photos is not None:
        res = evaluate(pred, photos, split="test", native=True, progress=False)
        row["photos_metric"], row["photos_separation"] = scores(res), separation(res, "images")
        row["photos_gap_auc"] = gap_auc(pred, photos, "test")
        found = shelves_found(res)
        row["photos_shelves"] = found[1] if found else None
        row["photos_shape"] = scores(evaluate(pred, photos, split="test", native=True, progress=False,
                                              scale_from_truth=True))
    if pred.cfg.decoder == "struct" and pred.cfg.struct_gap:
        pred.model.set_gap_cut(False)     # the same model, its boxes drawn without the gap cut
        try:
            res = evaluate(pred, args.data, split=args.split, limit=args.limit, progress=False)
            row["no_gap_cut"] = {"metric": scores(res), "separation": separation(res)}
            if photos is not None:
                res = evaluate(pred, photos, split="test", native=True, progress=False)
                row["no_gap_cut"].update(photos_metric=scores(res), photos_separation=separation(res, "images"))
        finally:
            pred.model.set_gap_cut(True)
    return row


def mean_rows(rows: list):
    """The mean of several runs' rows, key by key (numbers averaged, so counts may be fractional;
    a key missing or None in any run is None; strings from the first)."""
    first = rows[0]
    if isinstance(first, dict):
        keys = [k for k in first if all(isinstance(r, dict) and k in r for r in rows)]
        return {k: mean_rows([r[k] for r in rows]) for k in keys}
    if any(r is None for r in rows):
        return None
    if isinstance(first, (int, float)) and not isinstance(first, bool):
        return sum(rows) / len(rows)
    return first


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arm", action="append", required=True, metavar="NAME=RUN[,RUN...]",
                    help="an arm: a name and a `racklay train` run folder or a checkpoint file, or several "
                         "comma-separated (render draws / training seeds of one arm: scored each, averaged) (repeat)")
    ap.add_argument("--data", required=True, type=Path, help="RackLay dataset with the held-out split")
    ap.add_argument("--split", default="test", help="held-out split (default test)")
    ap.add_argument("--limit", type=int, default=None, help="only the first N images of the split")
    ap.add_argument("--photos", default=None, type=Path, help="annotate project of labelled photos to score too")
    ap.add_argument("--weights", default="best.safetensors", help="checkpoint inside each run (default best)")
    ap.add_argument("--calibrate-on", default=None, metavar="DATA:SPLIT",
                    help="also score each run with its decision biases fitted (`racklay calibrate`) on this split of "
                         "a RackLay dataset, e.g. the exported photos of other sites (/tmp/real:train), never the "
                         "split scored")
    ap.add_argument("--flip-average", action="store_true",
                    help="predict with test-time flip averaging (`racklay eval --flip-average`)")
    add_precision_args(ap)
    ap.add_argument("--json", default=None, help="also write the numbers here")
    args = ap.parse_args()
    if args.calibrate_on and not all(args.calibrate_on.rpartition(":")[::2]):
        ap.error(f"--calibrate-on {args.calibrate_on}: expected DATA:SPLIT, e.g. /tmp/real:train")

    from racklay import layout as L
    from racklay.predict import Predictor

    photos = None
    tmp = tempfile.TemporaryDirectory(prefix="racklay-ab-")
    if args.photos:
        from annotate.cli import main as annotate_main

        photos = Path(tmp.name) / "photos"
        if annotate_main(["export", str(args.photos), "--out", str(photos), "--split-fractions", "test=1"]) != 0:
            raise SystemExit(f"{args.photos}: annotate export failed")
    out = {}
    for item in args.arm:
        name, _, runs = item.partition("=")
        rows = []
        for run in runs.split(","):
            run = Path(run)
            ckpt = run if run.is_file() else run / args.weights
            pred = Predictor(str(ckpt), precision=args.precision, flip_average=args.flip_average)
            print(f"{name}: {ckpt} ({pred.cfg.decoder} decoder, {pred.precision})", file=sys.stderr, flush=True)
            rows.append(score_run(pred, run, args, photos))
        out[name] = mean_rows(rows)
        if len(rows) > 1:
            out[name]["runs"] = [{"run": r, "metric": row["metric"], "calibrated": row.get("calibrated")}
                                 for r, row in zip(runs.split(","), rows)]

    n = f"first {args.limit} of " if args.limit else ""
    print(f"\n{n}{args.data} [{args.split}]: dataset-level shelf, box IoU (top / front); paper-protocol mIoU")
    print("| arm | metric IoU | box AP | shape IoU (scale from truth) | paper mIoU rack/box top, front | "
          "channels separated (truth >= 2 box runs: both / truth; placed; predicted >= 2) | gap AUC (median per shelf; shelves) "
          "| CPU-min | best val | CPU-min per val point |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, r in out.items():
        m = r["metric"]
        paper = " / ".join(f"{m[v]['rack_mIoU']:.1f}, {m[v]['box_mIoU']:.1f}" for v in ("top", "front") if v in m)
        cpu, best = r["cpu_minutes"], r["best_val"]
        cost = (f"{'-' if cpu is None else f'{cpu:.0f}'} | {'-' if best is None else f'{best:.1f}'} | "
                f"{'-' if cpu is None or best is None else f'{cpu / max(best, 1e-9):.2f}'}")
        print(f"| {name} | {fmt(m)} | {fmt_ap(m)} | {fmt(r['shape'])} | {paper} | {sep_cell(r['separation'])} | {gap_cell(r['gap_auc'])} | {cost} |")
    print(f"(placed: the arm's gaps where the truth's are, within {L.GAP_TOLERANCE:.0%} of the shelf's length; "
          f"one cut in the middle of every shelf would place {centre_cut(args.data, args.split, args.limit, pred.layout_size)})")
    print("\ntargets (reproduction row, a model trained on complex): paper-protocol mIoU >= the paper's "
          "RackLay-D-disc, dataset-level box IoU >= 70 / 75")
    for name, r in out.items():
        m = r["metric"]
        cells = []
        for v in ("top", "front"):
            if v not in m:
                continue
            for cls, key in (("rack", "rack_mIoU"), ("box", "box_mIoU")):
                ref = PAPER_ROW[f"{v} {cls}"]
                cells.append(f"{v} {cls} {m[v][key]:.1f} vs {ref}: {'MET' if m[v][key] >= ref else 'NOT MET'}")
            b = m[v]["box"]
            cells.append(f"{v} box IoU {b:.1f} vs {BOX_TARGET[v]:g}: "
                         f"{'MET' if b >= BOX_TARGET[v] else f'NOT MET ({b - BOX_TARGET[v]:+.1f})'}")
        print(f"- {name}: " + "; ".join(cells))
    if photos is not None:
        print(f"\nlabelled photos ({args.photos}; arms trained on renders only): shelf, box IoU (top / front)")
        print("| arm | metric | box AP | scale from truth (targets: shelf >= 70, box >= 50) | "
              "photos with separate boxes (label and prediction / label; placed; prediction) | gap AUC | "
              "photos with >= 2 labelled shelves, all found / all; photos with fewer, more shelves than labelled |")
        print("|---|---|---|---|---|---|---|")
        for name, r in out.items():
            c = r["photos_shelves"]
            shelves = f"{c['multi_found']:g} / {c['multi']:g}; {c['fewer']:g}, {c['more']:g}" if c else "-"
            print(f"| {name} | {fmt(r['photos_metric'])} | {fmt_ap(r['photos_metric'])} | {fmt(r['photos_shape'])} | "
                  f"{sep_cell(r['photos_separation'])} | {gap_cell(r['photos_gap_auc'])} | {shelves} |")
        print(f"(one cut in the middle of every shelf would place {centre_cut(photos, 'test', None, None, True)})")
    if args.calibrate_on:
        print(f"\ncalibrated: each run's decision biases fitted on {args.calibrate_on} (racklay calibrate), then "
              f"{args.data.name} [{args.split}]: shelf, box IoU (top / front)")
        print("| arm | calibrated | as trained |")
        print("|---|---|---|")
        for name, r in out.items():
            print(f"| {name} | {fmt(r['calibrated'])} | {fmt(r['metric'])} |")
    multi = {name: r["runs"] for name, r in out.items() if "runs" in r}
    if multi:
        print(f"\narms of several runs (the tables show their means): each run's box IoU (box AP) on "
              f"{args.data.name} [{args.split}]")
        for name, runs in multi.items():
            print(f"- {name}: " + "; ".join(
                f"{r['run']} " + " / ".join(f"{r['metric'][v]['box']:.1f}" for v in ("top", "front") if v in r["metric"])
                + f" ({fmt_ap(r['metric'])})"
                + (", calibrated " + " / ".join(f"{r['calibrated'][v]['box']:.1f}" for v in ("top", "front"))
                   if r.get("calibrated") else "") for r in runs))
    cut_off = {name: r["no_gap_cut"] for name, r in out.items() if "no_gap_cut" in r}
    if cut_off:
        print("\nwith the gap cut off (boxes from the box output alone): shelf, box IoU (top / front); separated as above")
        print(f"| arm | {args.data.name} [{args.split}] | channels separated | photos | photos with separate boxes |")
        print("|---|---|---|---|---|")
        for name, r in cut_off.items():
            ph = (f"{fmt(r['photos_metric'])} | {sep_cell(r['photos_separation'])}" if "photos_metric" in r else "- | -")
            print(f"| {name} | {fmt(r['metric'])} | {sep_cell(r['separation'])} | {ph} |")
    tmp.cleanup()
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
