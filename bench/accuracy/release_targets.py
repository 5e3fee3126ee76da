"""The shipped model against the model issue's accuracy targets (docs/model-card.md).

  .venv/bin/python -m bench.accuracy.release_targets [--weights FILE] [--complex DIR] [--proxy-real DIR]

1. WareSynth `complex` test split (2,000 images never trained on: another seed than the release
   set, and another recipe; `--complex-recipe complex_paper` for the paper authors' box placement),
   scored at the data's own 512 x 512 resolution (`--native`):
   paper-protocol mIoU against the paper's RackLay-D-disc row (93.15 / 95.07 / 90.75 / 94.29)
   and dataset-level box IoU against >= 70 (top) and >= 75 (front).
2. Cross-domain, no fine-tuning: the proxy-real test split (100 images of `transfer`'s benchmark
   set): dataset-level shelf IoU >= 60 and box IoU >= 40 in both views.
3. The hand-labelled real photos of `datasets/real-photos/` (an `annotate` project, exported to a
   temporary RackLay dataset; its test split when the project's SOURCES.tsv gives a split per
   photo, all of them otherwise), scored at their own resolution: dataset-level IoU, precision,
   recall and AP, metric and of the shape alone (`--scale-from-truth`), on how many photos
   whose labels show separate boxes on a shelf the model shows them too, and how many labelled
   box stacks `racklay analyze` finds in place in the model's layouts (the same target graded:
   bench/accuracy/reasoning_validation.py's "stacks found in place"). The project's `holdout`
   split (HOLDOUT_SPLIT: photos of sites no released model was trained on, kept apart for release
   decisions) is scored the same way, after the test split.
4. The model issue's targets for the shipped model (SHIPPED_TARGETS: complex box IoU >= 60 / 70,
   proxy-real box IoU >= 45 / 50, real photos box IoU >= 35 / 35 and, shape alone, shelf >= 70 and
   box >= 50), the real-photo ones only for a model that never saw the photos nor others of their
   site: for the shipped model that is the holdout split.
Missing data sets are rendered first (about 3 min on 2 cores). Prints a table and MET / NOT MET;
asserts nothing. Precision follows the machine (`--precision auto`) unless set.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from annotate.dataset import HOLDOUT_SPLIT
from bench.common import PAPER_ROW, REPO, REPRODUCTION_BOX_TARGET
from racklay.predict import add_precision_args

NO_EXTRAS = ["--set", "write_depth=false", "--set", "write_normals=false", "--set", "write_semantic=false",
             "--set", "write_instance=false", "--set", "write_kitti=false", "--set", "write_coco=false"]


def skipped(path: Path) -> bool:
    """A set's folder option given as '' (which argparse's Path makes '.'): that set is not scored."""
    return str(path) in ("", ".")


def ensure(root: Path, args: list[str]) -> None:
    """Render the set at `root` with these `racklay synth` arguments unless it is there; a set
    there made with another recipe (its manifest's `recipe.name`) is refused in one line."""
    from racklay.data import SYNTH_MANIFEST

    recipe = args[args.index("--recipe") + 1]
    manifest = root / SYNTH_MANIFEST
    if manifest.is_file():
        made = json.loads(manifest.read_text()).get("recipe", {}).get("name")
        if made != recipe:
            raise SystemExit(f"{manifest}: {root} was rendered with recipe {made!r}, not {recipe!r}; "
                             f"give its recipe or another folder")
    if (root / "splits" / "test.txt").is_file():
        return
    cmd = [sys.executable, "-m", "racklay", "synth", "--out", str(root), "--no-progress", "--workers", "2", *args]
    print("rendering:", " ".join(cmd[2:]), flush=True)
    subprocess.run(cmd, check=True)


#: the photo splits scored (the holdout: sites kept apart from every training run, where the
#: real-photo targets can be scored honestly), each with the name its rows carry ("<name>" metric, "<name>, shape")
PHOTO_SETS = (("test", "real photos"), (HOLDOUT_SPLIT, "unseen sites"))
#: the model issue's targets for the shipped model: (set, class, {view: minimum dataset-level IoU});
#: a "real photos" target applies to every photo set of PHOTO_SETS
SHIPPED_TARGETS = [("complex", "box", {"top": 60.0, "front": 70.0}),
                   ("proxy-real", "box", {"top": 45.0, "front": 50.0}),
                   ("real photos", "box", {"top": 35.0, "front": 35.0}),
                   ("real photos, shape", "shelf", {"top": 70.0, "front": 70.0}),
                   ("real photos, shape", "box", {"top": 50.0, "front": 50.0})]


def print_model_issue_targets(rows: list[dict], seen: dict[str, bool]) -> None:
    """MET / NOT MET against SHIPPED_TARGETS. Real-photo targets count only for a photo set
    (`seen`: its name -> whether the model saw those photos or other photos of their sites) the
    model never saw (otherwise bench/accuracy/real_photo_cv.py gives the honest number)."""
    def value(set_, cls, view):
        for r in rows:
            if r["set"] != set_ or r["view"] != view:
                continue
            if f"{cls}_IoU" in r:
                return r[f"{cls}_IoU"]
            if r.get("class") == cls:
                return r["dataset_IoU"]
        return None

    print("\nthe model issue's targets for the shipped model (dataset-level IoU, top / front)")
    print("| set | class | target | measured | |")
    print("|---|---|---|---|---|")
    lines = []
    for target_set, cls, tgt in SHIPPED_TARGETS:
        if target_set.startswith("real photos"):
            sets = [(target_set.replace("real photos", name), name) for _, name in PHOTO_SETS]
        else:
            sets = [(target_set, None)]
        lines += [(set_, photos, cls, tgt) for set_, photos in sets]
    for set_, photos, cls, tgt in lines:
        got = {v: value(set_, cls, v) for v in tgt}
        if any(g is None for g in got.values()):
            continue
        if photos is not None and seen.get(photos, True):
            verdict = "in-sample or a seen site: see bench/accuracy/real_photo_cv.py"
        else:
            miss = [f"{v} {got[v] - tgt[v]:+.1f}" for v in tgt if got[v] < tgt[v]]
            verdict = "MET" if not miss else "NOT MET (" + ", ".join(miss) + ")"
        print(f"| {set_} | {cls} | >= {tgt['top']:g} / {tgt['front']:g} | {got['top']:.1f} / {got['front']:.1f} | {verdict} |")


def print_separate_boxes(truth_root: Path, pred_root: Path, split: str = "test") -> dict:
    """The model issue's "separate boxes where the photo shows separate boxes", counted: a photo
    shows them when some shelf of its front-view labels holds two or more box runs along x
    (`racklay.layout.box_runs`); the model shows them there when it separates that same shelf
    (a separation on another shelf is counted apart: it is what a phantom shelf looks like), and
    shows them in place when its gaps are the labels' (`racklay.layout.separated_shelves`)."""
    from racklay import layout as L
    from racklay.data import RackLayRoot

    truth, pred = RackLayRoot(truth_root), RackLayRoot(pred_root)
    want, got, placed, elsewhere, extra = [], [], [], [], []
    # the split, or its first --limit photos (the prediction root holds layouts, no images)
    for sid in [s for s in truth.resolve(split) if pred.layout_path("front", s).is_file()]:
        name = (truth.read_meta(sid) or {}).get("source_image", sid).split(".")[0]
        sep = L.separated_shelves(truth.read_layouts("front", sid), pred.read_layouts("front", sid))
        if sep.truth.any():
            want.append(name)
            if sep.hit.any():
                got.append(name)
                if sep.placed.any():
                    placed.append(name)
            elif sep.pred.any():
                elsewhere.append(name)
        elif sep.pred.any():
            extra.append(name)

    def names(xs):
        return ", ".join(xs[:6]) + (f", ... ({len(xs)})" if len(xs) > 6 else "") if xs else "-"

    also = f"; on another shelf than the labels' on {len(elsewhere)} ({names(elsewhere)})" if elsewhere else ""
    also += f"; on {len(extra)} where the labels show none ({names(extra)})" if extra else ""
    print(f"separate boxes (>= 2 box runs on a shelf, front view): the labels show them on {len(want)} photos; "
          f"the model on the same shelf on {len(got)} of these ({names(got)}), with its gaps where the labels "
          f"have theirs on {len(placed)} ({names(placed)}){also}")
    return {"labelled": want, "predicted": got, "placed": placed, "other_shelf": elsewhere, "extra": extra}


def photos_seen(rr, split: str, project: Path, meta: dict) -> bool:
    """Whether the model (its checkpoint `meta`) was fine-tuned on photos of `split` of the exported
    photos `rr`, or on other photos of their sites (by the project's SOURCES.tsv `site` column);
    prints which."""
    photos = {(rr.read_meta(s) or {}).get("source_image") for s in rr.resolve(split)}
    tuned = set(meta.get("fine_tuned_on_photos", []))
    if tuned & photos:
        print(f"IN-SAMPLE: this model was fine-tuned on {len(tuned & photos)} of these photos "
              f"({', '.join(sorted(tuned & photos)[:3])}, ...); bench/accuracy/real_photo_cv.py gives the "
              "estimate for photos from a source it has not seen")
        return True
    if tuned and (project / "SOURCES.tsv").is_file():
        from bench.accuracy.real_photo_cv import source_column

        site_of = source_column(project)
        sites = sorted({site_of[n] for n in photos if n in site_of} & {site_of[n] for n in tuned if n in site_of})
        if sites:
            print(f"SEEN SITE: this model was fine-tuned on other photos of these photos' sites ({', '.join(sites)}); "
                  "the scores above are for new views of a known site, not a new one "
                  "(bench/accuracy/real_photo_cv.py: sources it has not seen)")
            return True
    return False


def has_split_column(project: Path) -> bool:
    """Whether the photo project's SOURCES.tsv gives a split per photo (else every photo is `test`)."""
    src = project / "SOURCES.tsv"
    return src.is_file() and "split" in src.read_text(encoding="utf-8").split("\n", 1)[0].split("\t")


def print_stacks_in_place(project: Path, split: str, predictor, limit: int | None = None) -> dict:
    """The same target graded: the box stacks `racklay analyze` reads in the model's layouts of a
    photo split against the labelled stacks, by where they stand along their shelf
    (bench/accuracy/reasoning_validation.py: spans in fractions of the shelf, paired at IoU >= 0.5)."""
    from bench.accuracy.reasoning_validation import MATCH_IOU, photo_rows, summarise

    rows, _, _ = photo_rows(project, split if has_split_column(project) else "all", predictor, limit=limit)
    r = summarise(rows["predicted layouts"])
    print(f"box stacks found in place (`racklay analyze`'s reading of the model's layouts against the "
          f"{r['stacks_true']} labelled stacks, span along the shelf IoU >= {MATCH_IOU:g}): recall "
          f"{100 * r['stack_recall']:.1f} %, precision {100 * r['stack_precision']:.1f} % of the "
          f"{r['stacks_read']} read; the labels' own layouts read that way: recall "
          f"{100 * summarise(rows['ground-truth layouts'])['stack_recall']:.1f} %")
    return r


def report_photos(out: dict, name: str, split: str, real: Path, pred_root: Path, project: Path, meta: dict,
                  predictor=None, limit: int | None = None) -> list[dict]:
    """Print one photo split's scores (metric, shape alone, separate boxes, and with `predictor` the
    box stacks found in place); its rows for the targets."""
    r, sh = out[name]["result"], out[f"{name}, shape"]["result"]
    print(f"\nhand-labelled real photos ({project}, {split} split: {name}), {r['top']['images']} images, "
          "their own resolution")
    print("| view | shelf IoU | box IoU | box precision / recall | box AP | paper-protocol rack / box mIoU |")
    print("|---|---|---|---|---|---|")
    rows = []
    for view in ("top", "front"):
        d = r[view]["dataset"]
        print(f"| {view} | {100 * d['shelf']['IoU']:.2f} | {100 * d['box']['IoU']:.2f} | "
              f"{100 * d['box']['precision']:.1f} / {100 * d['box']['recall']:.1f} | {100 * d['box']['AP']:.2f} | "
              f"{100 * r[view]['paper']['rack']['mIoU']:.2f} / {100 * r[view]['paper']['box']['mIoU']:.2f} |")
        rows.append({"set": name, "view": view, "shelf_IoU": 100 * d["shelf"]["IoU"], "box_IoU": 100 * d["box"]["IoU"]})
    print("shape alone (each predicted shelf scaled to its labelled length, `racklay eval --scale-from-truth`): "
          + "; ".join(f"{v} shelf / box IoU {100 * sh[v]['dataset']['shelf']['IoU']:.2f} / "
                      f"{100 * sh[v]['dataset']['box']['IoU']:.2f}" for v in ("top", "front")))
    for view in ("top", "front"):
        d = sh[view]["dataset"]
        rows.append({"set": f"{name}, shape", "view": view, "shelf_IoU": 100 * d["shelf"]["IoU"],
                     "box_IoU": 100 * d["box"]["IoU"]})
    print_separate_boxes(real, pred_root, split)
    if predictor is not None:
        r = print_stacks_in_place(project, split, predictor, limit)
        out[name]["stacks_in_place"] = {k: r[k] for k in ("stacks_true", "stacks_read", "stack_recall", "stack_precision")}
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--weights", default=None, help="model (default: the shipped one)")
    ap.add_argument("--complex", default="/work/data/complex-test", type=Path,
                    help="WareSynth complex test set (rendered with seed 2027 if missing)")
    ap.add_argument("--complex-recipe", default="complex",
                    help="the recipe of that test set (default complex; complex_paper: the paper authors' "
                         "box placement; complex_paper_fixed: and their fixed rack size and camera); a set made "
                         "with another recipe is refused")
    ap.add_argument("--proxy-real", default="/work/data/proxy_real", type=Path,
                    help="proxy-real set of bench/accuracy/transfer_table2.sh (rendered with seed 1 if missing; "
                         "'' to skip: with --real-photos '' only the Table 1 row, as table1_cpu.sh prints it)")
    ap.add_argument("--real-photos", default=REPO / "datasets" / "real-photos", type=Path,
                    help="annotate project with the labelled real photos ('' to skip)")
    ap.add_argument("--limit", type=int, default=None, help="score only the first N test images of each set")
    ap.add_argument("--flip-average", action="store_true",
                    help="predict with test-time flip averaging (`racklay eval --flip-average`)")
    ap.add_argument("--json", default=None, help="also write the numbers here")
    add_precision_args(ap)
    args = ap.parse_args()

    from racklay.evaluate import evaluate
    from racklay.predict import Predictor
    from racklay.release import resolve_weights

    ensure(args.complex, ["--recipe", args.complex_recipe, "--n", "2000", "--seed", "2027", "--set", "splits={test: 1.0}", *NO_EXTRAS])
    with_proxy = not skipped(args.proxy_real)
    if with_proxy:
        ensure(args.proxy_real, ["--recipe", "proxy_real", "--n", "542", "--seed", "1", "--set", "layout_size=256"])
    weights = resolve_weights(args.weights)
    pred = Predictor(str(weights), precision=args.precision, flip_average=args.flip_average)
    print(f"model {weights} ({pred.precision}{', flip-averaged' if args.flip_average else ''}), input {pred.image_size[1]}x{pred.image_size[0]}, "
          f"layouts {pred.layout_size}", flush=True)
    out = {}
    tmp = tempfile.TemporaryDirectory(prefix="racklay-real-")
    sets = [("complex", args.complex, "test", True, False)]
    if with_proxy:
        sets.append(("proxy-real", args.proxy_real, "test", False, False))
    real = Path(tmp.name) / "real"
    photo_sets = []
    if not skipped(args.real_photos):
        from annotate.cli import main as annotate_main
        from racklay.data import RackLayRoot

        src = args.real_photos / "SOURCES.tsv"
        split_args = ["--split-file", str(src)] if has_split_column(args.real_photos) else ["--split-fractions", "test=1"]
        if annotate_main(["export", str(args.real_photos), "--out", str(real)] + split_args) != 0:
            raise SystemExit(f"{args.real_photos}: annotate export failed")
        photo_sets = [(split, name) for split, name in PHOTO_SETS if (real / "splits" / f"{split}.txt").is_file()]
        for split, name in photo_sets:
            sets += [(name, real, split, True, False), (f"{name}, shape", real, split, True, True)]
    for name, root, split, native, scale_from_truth in sets:
        t0 = time.time()
        pred_out = Path(tmp.name) / f"pred-{split}" if any(name == n for _, n in photo_sets) else None
        res = evaluate(pred, root, split=split, native=native, limit=args.limit, progress=True,
                       scale_from_truth=scale_from_truth, pred_out=pred_out)
        out[name] = {"result": res, "seconds": time.time() - t0}

    rows = []
    c = out["complex"]["result"]
    n = c["top"]["images"]
    print(f"\nWareSynth {args.complex_recipe} test split, {n} images, scored at the data's resolution")
    print("| cell | paper-protocol mIoU | paper RackLay-D-disc | dataset-level IoU | target |")
    print("|---|---|---|---|---|")
    for view in ("top", "front"):
        for cls, key in (("rack", "shelf"), ("box", "box")):
            m = 100 * c[view]["paper"][cls]["mIoU"]
            iou = 100 * c[view]["dataset"][key]["IoU"]
            ref = PAPER_ROW[f"{view} {cls}"]
            tgt = REPRODUCTION_BOX_TARGET[view] if cls == "box" else None
            ok_m = m >= ref
            line = f"| {view} {cls} | {m:.2f} ({'MET' if ok_m else f'NOT MET, {m - ref:+.2f}'}) | {ref:.2f} | {iou:.2f} |"
            line += (f" box IoU >= {tgt:g}: {'MET' if iou >= tgt else f'NOT MET ({iou - tgt:+.2f})'} |" if tgt else " - |")
            print(line)
            rows.append({"set": args.complex_recipe, "view": view, "class": cls, "paper_mIoU": m, "dataset_IoU": iou})
    if with_proxy:
        p = out["proxy-real"]["result"]
        print(f"\nproxy-real test split (cross-domain, no fine-tuning), {p['top']['images']} images")
        print("| view | shelf IoU (>= 60) | box IoU (>= 40) | paper-protocol rack / box mIoU |")
        print("|---|---|---|---|")
        for view in ("top", "front"):
            s, b = 100 * p[view]["dataset"]["shelf"]["IoU"], 100 * p[view]["dataset"]["box"]["IoU"]
            print(f"| {view} | {s:.2f} {'MET' if s >= 60 else f'NOT MET ({s - 60:+.2f})'} | "
                  f"{b:.2f} {'MET' if b >= 40 else f'NOT MET ({b - 40:+.2f})'} | "
                  f"{100 * p[view]['paper']['rack']['mIoU']:.2f} / {100 * p[view]['paper']['box']['mIoU']:.2f} |")
            rows.append({"set": "proxy-real", "view": view, "shelf_IoU": s, "box_IoU": b})
    seen = {}
    for split, name in photo_sets:
        rows += report_photos(out, name, split, real, Path(tmp.name) / f"pred-{split}", args.real_photos, pred.meta,
                              pred, args.limit)
        seen[name] = photos_seen(RackLayRoot(real), split, args.real_photos, pred.meta)
    if with_proxy or photo_sets:
        print_model_issue_targets(rows, seen)
    tmp.cleanup()
    if args.json:
        Path(args.json).write_text(json.dumps({"weights": str(weights), "rows": rows, "raw": out}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
