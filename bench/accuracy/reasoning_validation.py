"""Validate rack reasoning against known 3D boxes (issue 7).

For every image of a RackLay-format dataset whose meta/ID.json carries the 3D truth per visible
shelf (WareSynth; `racklay.toy` datasets too), compare what `racklay.reasoning` reads from

  * the ground-truth layouts (should be near exact: residuals are pixel quantisation, stacks
    merged at layout resolution, stacks hidden in the front view, the prism model of a stack), and
  * the layouts a trained model predicts from the photo (--weights, when a checkpoint exists),

with the truth: box-stack counts (exact-match accuracy and mean absolute error, per rack and per
shelf) and free volume (relative error per rack: |free_read - free_true| / free_true).

Truth per shelf: capacity = length x depth x clear height (what the layouts encode), occupied =
the sum of the boxes' own volumes, a stack = boxes whose footprints overlap.

    .venv/bin/python -m bench.accuracy.reasoning_validation --data datasets/waresynth-val --split test \
        --weights runs/accuracy-default/best.safetensors --json bench/results/reasoning.json
    .venv/bin/python -m bench.accuracy.reasoning_validation --toy 40     # no dataset: a D=512 toy set
    .venv/bin/python -m bench.accuracy.reasoning_validation --synth 200  # WareSynth scenes, no rendering
    .venv/bin/python -m bench.accuracy.reasoning_validation --photos datasets/real-photos --split test \
        --weights racklay/weights/racklay-lite0-struct-v11.safetensors --split-step 0 --split-step 0.08

--photos reads a labelled photo project (annotate): its truth is the labelled boxes (a stack =
labelled boxes whose footprints overlap; two cartons drawn side by side are two stacks), its layouts
are the project's own rasterisation; --split selects photos by SOURCES.tsv's split column (`all`:
every photo). --split-step (repeatable) compares racklay.reasoning's step split settings side by
side (0: connected components only).

--synth samples WareSynth scenes (racklay.synth.scene.sample_scene: the generator's own racks,
stacks and back rows) and rasterises their visible shelves with racklay.layout.rasterize_shelf
at D=512, as the generator does; it needs no renderer and no dataset on disk.

Prints Markdown tables; docs/reasoning.md records the numbers.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import markdown_table
from racklay import layout as L
from racklay.data import DataError, RackLayRoot
from racklay.predict import add_precision_args
from racklay.reasoning import ReasoningConfig, ShelfTruth, analyze_layouts, group_stacks

#: a read stack matches a true one when their spans along the shelf overlap by at least this IoU
MATCH_IOU = 0.5


def true_spans(t: ShelfTruth) -> list[tuple[float, float]]:
    """The truth's box stacks as spans along its shelf, in fractions of its length (0 = left end)."""
    out = []
    for group in group_stacks(t.boxes):
        lo = min(t.boxes[i].x_range()[0] for i in group)
        hi = max(t.boxes[i].x_range()[1] for i in group)
        out.append((lo / t.shelf.length + 0.5, hi / t.shelf.length + 0.5))
    return out


def read_spans(s) -> list[tuple[float, float]]:
    """A read shelf's box stacks as spans along it, in fractions of its read length: positions
    relative to the shelf, so a shelf read at the wrong metric size still matches by where its
    stacks stand."""
    x0, x1 = s.x
    n = max(x1 - x0, 1e-9)
    return [((b.x[0] - x0) / n, (b.x[1] - x0) / n) for b in s.boxes]


def matched_spans(a: list[tuple[float, float]], b: list[tuple[float, float]], iou: float = MATCH_IOU) -> int:
    """How many spans of `a` and `b` pair up one to one (greedy, highest 1-D IoU first) at >= iou."""
    pairs = []
    for i, (a0, a1) in enumerate(a):
        for j, (b0, b1) in enumerate(b):
            inter = min(a1, b1) - max(a0, b0)
            if inter > 0:
                pairs.append((inter / (max(a1, b1) - min(a0, b0)), i, j))
    used_a, used_b, n = set(), set(), 0
    for v, i, j in sorted(pairs, reverse=True):
        if v >= iou and i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            n += 1
    return n

BOX_FIELDS = ("cx", "cy", "sx", "sy", "sz", "z0", "yaw")


def truth_from_meta(meta: dict | None, source: str) -> list[ShelfTruth]:
    """Per visible shelf (lowest first, = layout channel): its Shelf and Boxes in the shelf frame.

    Two meta formats are read:
      * WareSynth (racklay.synth): rack.length / rack.depth, shelf_heights per channel, and
        objects with "channel", "size" [sx, sy, sz], "yaw" and "shelf_frame" {cx, cy, z0};
      * racklay.toy: shelves = [{length, depth, clear_height, boxes: [{cx, cy, sx, sy, sz, z0, yaw}]}].
    """
    rack = meta.get("rack") if isinstance(meta, dict) else None
    if isinstance(rack, dict) and (rack.get("layout_window") or rack.get("layout_heights")):
        raise DataError(f"{source}: its layouts draw only the part of the bay the image shows (recipe "
                        f"layout_extent: frame) and the meta's 3D truth is the whole bay: validate on a "
                        f"set rendered with layout_extent: bay")
    try:
        if meta and "objects" in meta and "rack" in meta and "shelf_heights" in meta:
            rack = meta["rack"]
            out = [ShelfTruth(L.Shelf(float(rack["length"]), float(rack["depth"]), float(h)), [])
                   for h in meta["shelf_heights"]]
            for o in meta["objects"]:
                ch, sf = o.get("channel"), o.get("shelf_frame")
                if ch is None or sf is None:
                    continue  # not on a visible shelf of the considered rack
                sx, sy, sz = (float(v) for v in o["size"])
                out[int(ch)].boxes.append(L.Box(cx=float(sf["cx"]), cy=float(sf["cy"]), sx=sx, sy=sy, sz=sz,
                                                z0=float(sf["z0"]), yaw=float(o.get("yaw", 0.0))))
            return out
        if meta and "shelves" in meta:
            out = []
            for s in meta["shelves"]:
                shelf = L.Shelf(float(s["length"]), float(s["depth"]), float(s["clear_height"]))
                out.append(ShelfTruth(shelf, [L.Box(**{f: float(b[f]) for f in BOX_FIELDS if f in b})
                                              for b in s["boxes"]]))
            return out
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise DataError(f"{source}: bad 3D truth in the meta ({type(e).__name__}: {e})") from None
    found = ", ".join(sorted(meta)) if meta else "no meta file"
    raise DataError(f"{source}: no 3D truth in the meta (WareSynth objects/rack or toy shelves); keys: {found}")


def compare(result, truth: list[ShelfTruth]) -> dict:
    """Per-rack and per-shelf numbers of one image (shelves matched by channel order)."""
    n_true = sum(t.n_stacks for t in truth)
    free_true = sum(t.free_m3 for t in truth)
    occ_true = sum(t.occupied_m3 for t in truth)
    cap_true = sum(t.capacity_m3 for t in truth)
    shelves = []
    for i, t in enumerate(truth):
        s = next((s for s in result.shelves if s.index == i), None)
        shelves.append({"true": t.n_stacks, "read": len(s.boxes) if s else 0,
                        "matched": matched_spans(true_spans(t), read_spans(s)) if s else 0,
                        "hidden": sum(b.hidden for b in s.boxes) if s else 0})
    return {"n_true": n_true, "n_read": result.n_box_stacks, "shelves_true": len(truth),
            "shelves_read": result.n_shelves, "free_true": free_true, "free_read": result.free_m3,
            "occ_true": occ_true, "occ_read": result.occupied_m3, "cap_true": cap_true,
            "cap_read": result.capacity_m3, "per_shelf": shelves}


def add_rows(rows: dict, configs: dict, truth: list[ShelfTruth], top, front, grid: L.Grid, pred: dict | None,
             sid: str) -> None:
    """Analyse one image's truth layouts (and prediction, if given) under every reasoning config and
    append the comparisons to rows[column name]."""
    for label, cfg in configs.items():
        sfx = f" ({label})" if label else ""
        gt = analyze_layouts(top, front, grid, cfg, source=sid)
        rows.setdefault("ground-truth layouts" + sfx, []).append(compare(gt, truth) | {"id": sid})
        if pred is not None:
            pr = analyze_layouts(pred.get("top"), pred.get("front"), pred["grid"], cfg, source=sid)
            rows.setdefault("predicted layouts" + sfx, []).append(compare(pr, truth) | {"id": sid})


def summarise(rows: list[dict]) -> dict:
    if not rows:
        return {}
    shelf = [s for r in rows for s in r["per_shelf"]]

    def rel(a, b):
        return [abs(r[a] - r[b]) / r[b] for r in rows if r[b] > 0]

    free_rel = rel("free_read", "free_true")
    return {
        "images": len(rows),
        "shelves": len(shelf),
        "stacks_true": sum(r["n_true"] for r in rows),
        "stacks_read": sum(r["n_read"] for r in rows),
        "shelf_count_acc": float(np.mean([r["shelves_read"] == r["shelves_true"] for r in rows])),
        "rack_count_acc": float(np.mean([r["n_read"] == r["n_true"] for r in rows])),
        "rack_count_mae": float(np.mean([abs(r["n_read"] - r["n_true"]) for r in rows])),
        "shelf_count_acc_by_shelf": float(np.mean([s["read"] == s["true"] for s in shelf])),
        "shelf_count_mae": float(np.mean([abs(s["read"] - s["true"]) for s in shelf])),
        "merged_shelves": int(sum(s["read"] < s["true"] for s in shelf)),
        "split_shelves": int(sum(s["read"] > s["true"] for s in shelf)),
        "hidden_stacks": int(sum(s["hidden"] for s in shelf)),
        "stack_recall": sum(s["matched"] for s in shelf) / max(sum(s["true"] for s in shelf), 1),
        "stack_precision": sum(s["matched"] for s in shelf) / max(sum(s["read"] for s in shelf), 1),
        "free_rel_err_mean": float(np.mean(free_rel)),
        "free_rel_err_median": float(statistics.median(free_rel)),
        "free_rel_err_max": float(np.max(free_rel)),
        "free_bias_mean": float(np.mean([(r["free_read"] - r["free_true"]) / r["free_true"] for r in rows
                                         if r["free_true"] > 0])),
        "capacity_rel_err_mean": float(np.mean(rel("cap_read", "cap_true"))),
        "occupied_rel_err_mean": float(np.mean(rel("occ_read", "occ_true"))),
    }


def table(results: dict[str, dict]) -> str:
    keys = [("images", "images", "{:d}"), ("shelves", "shelves (truth)", "{:d}"),
            ("stacks_true", "box stacks (truth)", "{:d}"), ("stacks_read", "box stacks (read)", "{:d}"),
            ("shelf_count_acc", "shelves per rack exact", "{:.1%}"),
            ("rack_count_acc", "stacks per rack exact", "{:.1%}"), ("rack_count_mae", "stacks per rack MAE", "{:.3f}"),
            ("shelf_count_acc_by_shelf", "stacks per shelf exact", "{:.1%}"),
            ("shelf_count_mae", "stacks per shelf MAE", "{:.3f}"),
            ("merged_shelves", "shelves with merged stacks", "{:d}"),
            ("split_shelves", "shelves with extra stacks", "{:d}"),
            ("hidden_stacks", "stacks flagged hidden", "{:d}"),
            ("stack_recall", f"stacks found in place: recall (span IoU >= {MATCH_IOU:g})", "{:.1%}"),
            ("stack_precision", "stacks found in place: precision (on the truth's shelves)", "{:.1%}"),
            ("free_rel_err_mean", "free volume rel. error, mean", "{:.2%}"),
            ("free_rel_err_median", "free volume rel. error, median", "{:.2%}"),
            ("free_rel_err_max", "free volume rel. error, max", "{:.2%}"),
            ("free_bias_mean", "free volume signed error, mean", "{:+.2%}"),
            ("capacity_rel_err_mean", "capacity rel. error, mean", "{:.2%}"),
            ("occupied_rel_err_mean", "occupied rel. error, mean", "{:.2%}")]
    names = list(results)
    rows = [[label] + [fmt.format(results[n][k]) if k in results[n] else "–" for n in names]
            for k, label, fmt in keys]
    return markdown_table(["metric"] + names, rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="RackLay dataset with 3D truth in meta/ID.json")
    ap.add_argument("--split", default="test")
    ap.add_argument("--toy", type=int, default=0, help="instead of --data: build a toy set of N images at D=512")
    ap.add_argument("--synth", type=int, default=0,
                    help="instead of --data: N WareSynth scenes rasterised at D=512 (no photos, no model)")
    ap.add_argument("--recipe", default=None, help="WareSynth recipe for --synth (default: built-in defaults)")
    ap.add_argument("--seed", type=int, default=0, help="toy / synth seed")
    ap.add_argument("--size", type=int, default=None,
                    help="resize the ground-truth layouts to S x S first (e.g. 256, the model's output size)")
    ap.add_argument("--weights", default=None, help="checkpoint for predicted layouts (skipped when absent)")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--json", default=None, help="write the numbers here")
    ap.add_argument("--photos", default=None, help="instead of --data: a labelled photo project (annotate)")
    ap.add_argument("--split-step", type=float, action="append", default=None, metavar="M",
                    help="racklay.reasoning split_step_m; repeat to compare settings (default: "
                         f"{ReasoningConfig().split_step_m})")
    ap.add_argument("--slope-fraction", type=float, action="append", default=None, metavar="F",
                    help="racklay.reasoning slope_fraction (0: the step split cuts slopes into staircases); "
                         f"repeat to compare (default: {ReasoningConfig().slope_fraction})")
    ap.add_argument("--load-width", type=float, action="append", default=None, metavar="M",
                    help="racklay.reasoning load_width_m (0: not known, the step cut reads the stacks); repeat to "
                         "compare")
    add_precision_args(ap)
    args = ap.parse_args(argv)

    steps = args.split_step or [ReasoningConfig().split_step_m]
    slopes = args.slope_fraction or [ReasoningConfig().slope_fraction]
    loads = args.load_width or [ReasoningConfig().load_width_m]
    args.configs = {", ".join(([f"step {st:g} m"] if len(steps) > 1 else []) + ([f"slope {sf:g}"] if len(slopes) > 1 else [])
                              + ([f"loads {lw:g} m"] if len(loads) > 1 else [])):
                    ReasoningConfig(split_step_m=st, slope_fraction=sf, load_width_m=lw)
                    for st in steps for sf in slopes for lw in loads}
    if args.synth:
        return synth_main(args)
    if args.photos:
        return photos_main(args)
    tmp = None
    if args.data:
        ds = RackLayRoot(args.data)
    elif args.toy:
        from racklay.toy import build_toy_dataset

        tmp = tempfile.TemporaryDirectory(prefix="racklay-toy-")
        ds = build_toy_dataset(Path(tmp.name) / "toy", n=args.toy, seed=args.seed, D=512)
        print(f"toy dataset: {args.toy} images at D=512 (seed {args.seed})")
    else:
        ap.error("give --data ROOT or --toy N")
    ids = ds.resolve(args.split)[: args.limit]
    predictor = None
    if args.weights:
        if Path(args.weights).is_file():
            from racklay.predict import Predictor

            predictor = Predictor(args.weights, precision=args.precision)
            print(f"predicted layouts from {args.weights} (S={predictor.layout_size})")
        else:
            print(f"{args.weights}: no checkpoint, predicted layouts skipped")

    rows = {}
    t0 = time.perf_counter()
    errors = 0
    for n, sid in enumerate(ids):
        try:
            truth = truth_from_meta(ds.read_meta(sid), str(ds.meta_path(sid)))
            top, front = ds.read_layouts("top", sid), ds.read_layouts("front", sid)
            meta = ds.read_meta(sid) or {}
            extent = float((meta.get("grid") or {}).get("extent_m", L.DEFAULT_EXTENT_M))
            if args.size:
                top, front = L.resize_layouts(top, args.size), L.resize_layouts(front, args.size)
            pred = predictor.predict(ds.read_image(sid)) if predictor else None
            add_rows(rows, args.configs, truth, top, front, L.Grid(top.shape[-1], extent), pred, sid)
        except (DataError, L.LayoutError) as e:
            errors += 1
            print(f"error: {e}", file=sys.stderr)
        if (n + 1) % 50 == 0:
            print(f"  {n + 1}/{len(ids)} images, {time.perf_counter() - t0:.0f} s", flush=True)
    dt = time.perf_counter() - t0
    results = {k: summarise(v) for k, v in rows.items() if v}
    print(f"\n{ds.root} split {args.split}: {len(ids)} images ({errors} unreadable), {dt:.1f} s "
          f"(2 shared CPU cores, other jobs running)\n")
    if results:
        print(table(results))
    worst = sorted(next(iter(rows.values()), []), key=lambda r: -abs(r["free_read"] - r["free_true"]) / max(r["free_true"], 1e-9))[:5]
    print("\nworst ground-truth-layout images (free volume):")
    for r in worst:
        print(f"  {r['id']}: free read {r['free_read']:.3f} vs true {r['free_true']:.3f} m³, "
              f"stacks {r['n_read']} vs {r['n_true']}")
    if args.json:
        from racklay.atomic import atomic_write_json

        atomic_write_json(args.json, {"data": str(ds.root) if not tmp else f"toy n={args.toy} seed={args.seed}",
                                      "split": args.split, "weights": args.weights if predictor else None,
                                      "results": results, "per_image": rows})
    if tmp:
        tmp.cleanup()
    return 1 if errors and not results else 0


def synth_main(args) -> int:
    """Validate on WareSynth scene contents rasterised at D=512 (ground-truth layouts only)."""
    from racklay.synth.recipe import Recipe, load_recipe
    from racklay.synth.scene import sample_scene

    recipe = load_recipe(args.recipe) if args.recipe else Recipe()
    grid = L.Grid(512, recipe.extent_m)
    rows, t0, t_an = {}, time.perf_counter(), 0.0
    for i in range(args.synth):
        scene = sample_scene(recipe, args.seed, i)
        inputs = scene.layout_inputs()
        per = [L.rasterize_shelf(sh, boxes, grid) for sh, boxes in inputs]
        top, front = L.stack_shelves(per, recipe.R, grid)
        g = grid
        if args.size:
            top, front = L.resize_layouts(top, args.size), L.resize_layouts(front, args.size)
            g = L.Grid(args.size, grid.extent)
        t1 = time.perf_counter()
        truth = [ShelfTruth(sh, list(boxes)) for sh, boxes in inputs]
        add_rows(rows, args.configs, truth, top, front, g, None, f"scene{i:05d}")
        t_an += time.perf_counter() - t1
    dt = time.perf_counter() - t0
    results = {k: summarise(v) for k, v in rows.items()}
    n = len(next(iter(rows.values()), []))
    print(f"WareSynth scenes (recipe {recipe.name}, seed {args.seed}): {n} racks, layouts at "
          f"D={args.size or 512}, "
          f"{dt:.1f} s total, analysis {t_an / max(n * len(rows), 1) * 1000:.0f} ms per rack and setting "
          f"(2 shared CPU cores, other jobs running)\n")
    print(table(results))
    worst = sorted(next(iter(rows.values())), key=lambda r: -abs(r["free_read"] - r["free_true"]) / max(r["free_true"], 1e-9))[:5]
    print("\nworst racks (free volume):")
    for r in worst:
        print(f"  {r['id']}: free read {r['free_read']:.3f} vs true {r['free_true']:.3f} m³, "
              f"occupied read {r['occ_read']:.3f} vs true {r['occ_true']:.3f}, stacks {r['n_read']} vs {r['n_true']}")
    if args.json:
        from racklay.atomic import atomic_write_json

        atomic_write_json(args.json, {"data": f"WareSynth scenes n={args.synth} seed={args.seed} recipe={recipe.name}",
                                      "results": results, "per_image": rows})
    return 0


def photo_rows(project, split: str, predictor=None, configs: dict | None = None, limit: int | None = None
               ) -> tuple[dict, list[str], L.Grid]:
    """The comparisons (`add_rows`) of a labelled photo project's `split`: truth = the labelled boxes,
    layouts = their rasterisation, predictions (with a racklay.predict.Predictor) as the annotation
    tool makes them (the photo as taken). Returns (rows by column name, the photos, the grid)."""
    from annotate import dataset as DS
    from annotate.editor import Tool
    from annotate.store import Project
    from bench.common import labelled_photos

    proj = Project(project)
    names = labelled_photos(proj, split, limit)
    tool = Tool(proj, predictor) if predictor is not None else None
    st = proj.settings
    grid = L.Grid(st["D"], st["extent"])
    rows: dict = {}
    for name in names:
        ann = proj.load(name)
        top, front, scene = DS.annotation_layouts(proj, ann)
        truth = [ShelfTruth(sh, scene.layout_boxes(i)) for i, sh in enumerate(scene.shelves())]
        add_rows(rows, configs or {"": ReasoningConfig()}, truth, top, front, grid,
                 tool.prediction(name) if tool else None, name)
    return rows, names, grid


def photos_main(args) -> int:
    """Validate on a labelled photo project (`photo_rows`)."""
    predictor = None
    if args.weights:
        from racklay.predict import Predictor

        predictor = Predictor(args.weights, precision=args.precision)
    t0 = time.perf_counter()
    rows, names, grid = photo_rows(args.photos, args.split, predictor, args.configs, args.limit)
    results = {k: summarise(v) for k, v in rows.items()}
    print(f"{args.photos} split {args.split}: {len(names)} labelled photos, layouts at D={grid.size}"
          f"{', predictions by ' + args.weights if predictor else ''}; {time.perf_counter() - t0:.0f} s\n")
    print(table(results))
    if args.json:
        from racklay.atomic import atomic_write_json

        atomic_write_json(args.json, {"data": args.photos, "split": args.split, "weights": args.weights,
                                      "results": results, "per_image": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
