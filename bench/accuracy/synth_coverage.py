"""Coverage report: does a WareSynth recipe cover what the labelled real photos show?

For every labelled photo of an `annotate` project (default `datasets/real-photos/`) the metric
scene is rebuilt from its annotation (`annotate.geometry`: rack size, shelf boards, boxes, and the
camera recovered from the rack's homography), and the same quantities are measured on scenes
sampled from each recipe (`racklay.synth.scene.sample_scene`, no rendering):

    rack length (as far as the layouts draw it: the bay, or with `layout_extent: frame` / `row`
    the part of the bay / row in the image, as a labelled photo draws it), rack depth, visible
    shelves, level height (board to board, shelves below the top one), box width / height /
    depth, box run width (boxes on one shelf that touch or overlap along it, less than RUN_GAP
    apart, merged: what the front layout draws as one run and what a labeller draws as one box
    for a wall of cartons), the gap between neighbouring runs, the fraction of each level's drawn
    length under loads (empty levels 0; a full pallet bay 0.85-0.99), camera distance to the rack front,
    camera height, focal length per pixel of image width; and the framing, which every photo
    determines (near-frontal ones too): the width in the image of the part of the bay that the
    layouts draw (at the height of the middle of its levels) over the image width (a labelled
    photo draws the bay as far as the photo shows it, so at most 1; a recipe with `layout_extent:
    bay` draws the whole bay, also where it overflows the frame), the height of its levels (lowest
    board to the top of the highest level, at the drawn part's middle) over the image height, and
    how far the drawn part's centre lies from the image's centre.

It prints, per recipe and quantity, the recipe's 5-95 % and min-max range, its median and the
photos' (the support can hold every photo while the bulk of the renders sits elsewhere), how
many photo values fall inside [min, max] (the recipe's support) and which photos fall outside, and draws one panel
per quantity (recipe histograms over every photo value and the recipes' middle 99 %, their far
tails piled into the end bins; photo values as ticks; red = outside every recipe given).

    .venv/bin/python -m bench.accuracy.synth_coverage --recipe complex --recipe pallet [--n 2000] [--set KEY=VALUE]
        [--project datasets/real-photos] [--out docs/img/synth_coverage.png]

Numbers only; nothing is asserted. The camera of a near-frontal photo is not determined by its
rack (a typical phone focal length is then assumed): such photos are left out of the focal and
distance rows and counted in the header. A labelled box that the photo's edge cuts shows only
part of its width (height), so its width and its run (its height) are not counted either
(`annotate.geometry.cut_by_frame`); the recipes' objects are measured whole.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.common import REPO

QUANTITIES = {   # key: (label, unit)
    "rack_length": ("rack length", "m"),
    "rack_depth": ("rack depth", "m"),
    "shelves": ("visible shelves", ""),
    "level_height": ("level height", "m"),
    "box_width": ("box width", "m"),
    "run_width": ("box run width", "m"),
    "load_cover": ("level length under loads", ""),
    "run_gap": ("gap between box runs", "m"),
    "box_height": ("box height", "m"),
    "box_depth": ("box depth", "m"),
    "cam_distance": ("camera distance", "m"),
    "cam_height": ("camera height", "m"),
    "focal": ("focal / image width", ""),
    "bay_span": ("bay width / image width", ""),
    "band_span": ("levels' height / image height", ""),
    "bay_offset": ("bay centre from image centre / image width", ""),
}


#: boxes closer than this along a shelf count as one run (about one cell of the 512² layout grid,
#: 8 m / 512 = 1.6 cm: the layout cannot show a narrower gap)
RUN_GAP = 0.02


def run_spans(intervals) -> list[tuple[float, float]]:
    """The (x0, x1) runs that [x0, x1) intervals along one shelf form when those less than
    RUN_GAP apart (or overlapping, e.g. stacked) are merged, left to right."""
    runs: list[list[float]] = []
    for x0, x1 in sorted(intervals):
        if runs and x0 - runs[-1][1] < RUN_GAP:
            runs[-1][1] = max(runs[-1][1], x1)
        else:
            runs.append([x0, x1])
    return [(a, b) for a, b in runs]


def run_widths(intervals) -> list[float]:
    """Widths of the runs of `run_spans`."""
    return [x1 - x0 for x0, x1 in run_spans(intervals)]


def run_gaps(intervals, x0: float = -np.inf, x1: float = np.inf) -> list[float]:
    """The empty stretches between neighbouring runs of `run_spans` (each >= RUN_GAP), those that
    lie within x0..x1 (the part of the level the layouts draw): what the front layout must draw as
    background between two loads."""
    runs = run_spans(intervals)
    return [b0 - a1 for (_, a1), (b0, _) in zip(runs, runs[1:]) if a1 >= x0 and b0 <= x1]


def load_cover(intervals, x0: float, x1: float, snap: float = 0.0) -> float:
    """The fraction of a level's drawn stretch x0..x1 that loads stand on (their x-spans' union);
    a load within `snap` of an end reaches it, as the annotator snaps a labelled box's side
    (`annotate.geometry.snap_edges`), so that renders are measured as a labeller draws them."""
    spans = [(x0 if a < x0 + snap else a, x1 if b > x1 - snap else b) for a, b in intervals]
    spans = [(max(a, x0), min(b, x1)) for a, b in run_spans(spans)]
    return sum(max(0.0, b - a) for a, b in spans) / (x1 - x0)


def framing_quantities(to_image, x0: float, x1: float, lo: float, hi: float, w: int, h: int) -> dict:
    """bay_span, band_span and bay_offset (see the module's doc) of the part x0..x1 of a bay that
    the layouts draw, from a map of rack-front points (x along the bay, z up; metres) to pixels,
    its levels' bottom and top heights and the image size."""
    mid, xm = (lo + hi) / 2, (x0 + x1) / 2
    (xl, _), (xr, _), (_, yb), (_, yt) = to_image([[x0, mid], [x1, mid], [xm, lo], [xm, hi]])
    return {"bay_span": [abs(xr - xl) / w], "band_span": [abs(yb - yt) / h],
            "bay_offset": [((xl + xr) / 2 - w / 2) / w]}


def photo_quantities(project: Path) -> tuple[dict, list[str]]:
    """{photo name: {quantity: [values]}} from the project's annotations, and notes."""
    from annotate import geometry as G
    from annotate.schema import load_annotation, load_settings, pixel_aspect

    settings = load_settings(project / "project.json")
    aspect = pixel_aspect(settings)
    out, notes = {}, []
    cut_total = cut_photos = 0
    for path in sorted((project / "annotations").glob("*.json")):
        ann = load_annotation(path)
        name = ann["image"]
        try:
            sc = G.build_scene(ann, settings)
        except G.GeometryError as e:
            notes.append(f"{name}: left out ({e})")
            continue
        q = {k: [] for k in QUANTITIES}
        q["rack_length"] = [sc.width]
        q["rack_depth"] = [sc.depth]
        q["shelves"] = [len(sc.shelf_v)]
        q["level_height"] = list(np.diff(sc.shelf_v))
        cut = {b.id: G.cut_by_frame(sc.plane, b, ann["image_size"]) for b in sc.boxes}
        for b in sc.boxes:
            # a box the photo's edge cuts shows only part of its width (height): not its size
            if not cut[b.id][0]:
                q["box_width"].append(b.u1 - b.u0)
            if not cut[b.id][1]:
                q["box_height"].append(b.v1 - b.v0)
            q["box_depth"].append(b.depth)
        n_cut = sum(c[0] for c in cut.values())
        q["load_cover"] = [load_cover([(b.u0, b.u1) for b in sc.boxes if b.shelf == k], 0.0, sc.width)
                           for k in range(len(sc.shelf_v))]
        for k in {b.shelf for b in sc.boxes if b.shelf is not None}:
            on = [b for b in sc.boxes if b.shelf == k]
            spans = [(b.u0, b.u1) for b in on]
            cut_spans = [(b.u0, b.u1) for b in on if cut[b.id][0]]
            q["run_width"] += [x1 - x0 for x0, x1 in run_spans(spans)
                               if not any(x0 - 1e-9 <= c0 and c1 <= x1 + 1e-9 for c0, c1 in cut_spans)]
            q["run_gap"] += run_gaps(spans)              # between two seen loads, so seen whole
        lo, hi = sc.shelf_v[0], sc.shelf_v[-1] + sc.clear[-1]
        w, h = ann["image_size"]
        q.update(framing_quantities(sc.plane.to_image, 0.0, sc.width, lo, hi, w, h))
        cut_total += n_cut
        cut_photos += n_cut > 0
        cam = G.camera_from_plane(sc.plane, ann["image_size"], aspect)
        if cam.focal_from_photo:
            c = cam.center                # rack frame: x along, y into the rack, z up from its bottom
            q["cam_distance"] = [float(-c[1])]
            q["cam_height"] = [float(c[2])]
            q["focal"] = [float(cam.K[1, 1] / (ann["image_size"][0] * aspect))]
        else:
            notes.append(f"{name}: near-frontal, camera not determined (no distance / height / focal)")
        out[name] = q
    if cut_total:
        notes.append(f"{cut_total} boxes on {cut_photos} photos are cut by the photo's left or right edge (their "
                     f"widths and runs not counted); boxes the top or bottom edge cuts have their heights left out")
    return out, notes


def recipe_quantities(name: str, n: int, seed: int, sets=(), snap: float = 0.0) -> dict:
    """The QUANTITIES of n scenes sampled from a recipe; `snap`: the labelling project's box snap
    (metres), applied to the loads' ends when measuring load_cover."""
    from racklay.synth.recipe import load_recipe
    from racklay.synth.scene import sample_scene

    r = load_recipe(name, list(sets))
    q = {k: [] for k in QUANTITIES}
    for i in range(n):
        s = sample_scene(r, seed, i)
        x0, x1 = s.layout_window or (-s.rack_length / 2, s.rack_length / 2)
        q["rack_length"].append(x1 - x0)         # as far as the layouts draw it, as a labelled photo's
        q["rack_depth"].append(s.rack_depth)
        q["shelves"].append(len(s.visible))
        tops = [s.shelves[k].board_top for k in s.visible]
        q["level_height"] += list(np.diff(tops))
        for k in s.visible:
            spans = []
            for j in s.shelves[k].items:
                b = s.objects[j].layout_box
                q["box_width"].append(b.sx)
                q["box_height"].append(b.z0 + b.sz)     # a stack's height above its board
                q["box_depth"].append(b.sy)
                spans.append(b.x_range())                # its footprint along x (yaw included)
            q["run_width"] += run_widths(spans)
            q["run_gap"] += run_gaps(spans, x0, x1)
            q["load_cover"].append(load_cover(spans, x0, x1, snap))
        lo = s.shelves[s.visible[0]].board_top
        top = s.shelves[s.visible[-1]]

        def to_image(pts, cam=s.camera, y=-s.rack_depth / 2):
            return cam.project([[x, y, z] for x, z in pts])

        drawn = (s.layout_heights or [None])[-1]              # the top level as far as the layouts draw it
        hi = top.board_top + (top.clear_height if drawn is None else drawn)
        for k, v in framing_quantities(to_image, x0, x1, lo, hi, s.camera.width, s.camera.height).items():
            q[k] += v
        c = s.camera.center
        q["cam_distance"].append(float(-s.rack_depth / 2 - c[1]))
        q["cam_height"].append(float(c[2]))
        q["focal"].append(float(s.camera.K[0, 0] / s.camera.width))
    return q


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recipe", action="append", default=None, help="recipe name or YAML path (repeatable; "
                    "default: complex, release, pallet)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a recipe key for every recipe, as `racklay synth --set` does (repeatable)")
    ap.add_argument("--n", type=int, default=1500, help="scenes sampled per recipe (default 1500)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--project", type=Path, default=REPO / "datasets" / "real-photos", help="annotate project folder")
    ap.add_argument("--out", default=None, help="write the figure here (PNG)")
    args = ap.parse_args(argv)
    recipes = args.recipe or ["complex", "release", "pallet"]

    photos, notes = photo_quantities(args.project)
    print(f"{len(photos)} labelled photos in {args.project}")
    for line in notes:
        print(f"  note: {line}")
    from racklay.synth.recipe import RecipeError

    try:
        from annotate.geometry import box_snap
        from annotate.schema import load_settings
        snap = box_snap(load_settings(args.project / "project.json"))
        rq = {name: recipe_quantities(name, args.n, args.seed, args.set, snap) for name in recipes}
    except RecipeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2

    support = {name: {k: (float(np.min(rq[name][k])), float(np.max(rq[name][k]))) for k in QUANTITIES}
               for name in recipes}

    def inside(name, key, x):
        lo, hi = support[name][key]
        return lo - 1e-9 <= x <= hi + 1e-9

    for name in recipes:
        print(f"\nrecipe {name} ({args.n} scenes, seed {args.seed})")
        print("| quantity | recipe 5-95 % | recipe min-max | recipe median; photos' | photo values inside | "
              "photos outside |")
        print("|---|---|---|---|---|---|")
        for key, (label, unit) in QUANTITIES.items():
            p5, p95 = np.percentile(rq[name][key], [5, 95])
            lo, hi = support[name][key]
            flags = {photo: [inside(name, key, x) for x in q[key]] for photo, q in photos.items()}
            n_in = sum(sum(f) for f in flags.values())
            total = sum(len(f) for f in flags.values())
            bad = [photo.split(".")[0] for photo, f in flags.items() if not all(f)]
            u = f" {unit}" if unit else ""
            pv = [x for q in photos.values() for x in q[key]]
            med = f"{np.median(rq[name][key]):.2f}; {np.median(pv):.2f}" if pv else "-"
            print(f"| {label} | {p5:.2f}-{p95:.2f}{u} | {lo:.2f}-{hi:.2f}{u} | {med} | {n_in} / {total} | "
                  f"{', '.join(bad) if bad else '-'} |")

    # values no recipe given covers: the union's gaps
    uncovered = {key: {photo: [x for x in q[key] if not any(inside(n, key, x) for n in recipes)]
                       for photo, q in photos.items()} for key in QUANTITIES}
    print(f"\nphoto values outside every recipe given ({', '.join(recipes)}):")
    print("| quantity | values outside / all | photos (their values outside) |")
    print("|---|---|---|")
    for key, per in uncovered.items():
        n_out = sum(len(v) for v in per.values())
        total = sum(len(q[key]) for q in photos.values())
        listed = "; ".join(f"{p.split('.')[0]} ({', '.join(f'{x:.2f}' for x in v)})" for p, v in per.items() if v)
        print(f"| {QUANTITIES[key][0]} | {n_out} / {total} | {listed or '-'} |")
    n_photos_out = sum(1 for photo in photos if any(uncovered[k][photo] for k in QUANTITIES))
    print(f"\nphotos with a value outside every recipe: {n_photos_out} of {len(photos)}")

    if args.out:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from racklay.viz import save_figure

        keys = list(QUANTITIES)
        ncol = (len(keys) + 1) // 2
        fig, axes = plt.subplots(2, ncol, figsize=(3.6 * ncol, 6.5))
        for ax in axes.ravel()[len(keys):]:
            ax.set_visible(False)
        for ax, key in zip(axes.ravel(), keys):
            label, unit = QUANTITIES[key]
            # the range: every photo value and the recipes' middle 99 % (their far tails, e.g. a bay
            # 200 image widths wide seen from 35 cm, piled into the end bins)
            pv = np.concatenate([np.asarray(q[key], float) for q in photos.values()] + [np.zeros(0)])
            rv = [np.asarray(rq[n][key], float) for n in recipes]
            lo = min([*pv, *(np.percentile(v, 0.5) for v in rv)])
            hi = max([*pv, *(np.percentile(v, 99.5) for v in rv)])
            bins = np.linspace(lo, hi + 1e-6, 30) if key != "shelves" else np.arange(0.5, 6.5)
            for name, v in zip(recipes, rv):
                ax.hist(np.clip(v, bins[0], bins[-1]), bins=bins, density=True, alpha=0.45, label=name)
            for photo, q in photos.items():
                for x in q[key]:
                    out = x in uncovered[key][photo]
                    ax.axvline(x, ymin=0, ymax=0.12, color="red" if out else "black", lw=1.2)
            ax.set_title(label + (f" ({unit})" if unit else ""), fontsize=10)
            ax.set_yticks([])
        axes[0, 0].legend(fontsize=8)
        fig.suptitle("WareSynth recipes (histograms) vs labelled real photos (ticks; red = outside every recipe)",
                     fontsize=11)
        fig.tight_layout()
        save_figure(fig, args.out, dpi=80)
        print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
