"""Generate a WareSynth dataset: sample -> render -> ground truth -> write, per index.

Every image depends only on (recipe, seed, index): shards (`index % n == i`) and worker
processes produce byte-identical files, so shards merge by copying folders together. A run
resumes: an index whose meta/NNNNNN.json exists is finished (meta is written last, every
file through racklay.atomic). At the end, split files and COCO annotations are (re)built from
the finished samples found in the folder.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import layout as L
from ..atomic import atomic_save_npy, atomic_write_bytes, atomic_write_json, atomic_write_text, encode_png
from ..data import SYNTH_MANIFEST, RackLayRoot, make_splits
from .recipe import Recipe, recipe_from_dict

MANIFEST = SYNTH_MANIFEST
#: the per-sample files beside the RackLay ones: folder -> file suffix (folder/NNNNNN.suffix)
EXTRA_FILES = {"depth": ".png", "normals": ".png", "semantic": ".png", "instance": ".png", "kitti": ".txt"}
STAGES = ("sample", "render", "groundtruth", "write")


def extra_path(root: Path, kind: str, sid: str) -> Path:
    """Where a sample's extra file of this kind (EXTRA_FILES) lies in the dataset folder `root`."""
    return root / kind / f"{sid}{EXTRA_FILES[kind]}"


def sample_id(index: int) -> str:
    return f"{index:06d}"


def parse_shard(text: str | None) -> tuple[int, int]:
    if not text:
        return 0, 1
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise ValueError(f"--shard {text!r}: expected i/n, e.g. 0/4") from None
    if n < 1 or not 0 <= i < n:
        raise ValueError(f"--shard {text!r}: need 0 <= i < n")
    return i, n


def render_padding(recipe: Recipe) -> tuple[int, int]:
    """Extra pixels rendered on each side (x, y) so that barrel distortion (k1 < 0) never
    samples outside the rendered frame: the largest over the recipe's focal lengths, each with the
    strongest k1 it can get (the recipe's, bounded by effects.k1_limit as sample_scene bounds it)."""
    from .effects import k1_limit, undistort_normalised

    k1_min = min(recipe.distortion_k1[0], 0.0)
    if k1_min == 0:
        return 0, 0
    W, H = recipe.image_width, recipe.image_height
    px = py = 0
    for f in np.linspace(recipe.focal_px[0], recipe.focal_px[1], 33):
        K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
        k1 = max(k1_min, k1_limit(K, W, H))
        xd, yd = W / 2 / f, H / 2 / f
        xu, yu = undistort_normalised(xd, yd, k1)
        px, py = max(px, int(np.ceil((xu - xd) * f)) + 2), max(py, int(np.ceil((yu - yd) * f)) + 2)
    return px, py


#: pixels kept around the part of the render that the lens distortion reads (source_region):
#: bilinear reads one pixel on, edge anti-aliasing looks one pixel farther
REGION_MARGIN = 3


def source_region(maps, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): the part of a render of `size` (width, height) that the distortion
    `maps` (effects.distortion_maps) read, with REGION_MARGIN pixels around it (or one more, for
    an even origin), clipped to the render. Only that part is drawn: the rest of the padding
    that the recipe's widest barrel lens needs is wasted on a narrower or a pincushion one."""
    mx, my = maps
    W, H = size
    m = REGION_MARGIN
    # an even origin: shifting the maps by it keeps nearest-neighbour rounding (ties to even)
    x0, y0 = (max(0, int(np.floor(a.min())) - m) // 2 * 2 for a in (mx, my))
    return x0, y0, min(W, int(np.ceil(mx.max())) + 1 + m), min(H, int(np.ceil(my.max())) + 1 + m)


class Generator:
    """Renders and writes samples of one dataset; one per process (owns a GL context)."""

    def __init__(self, recipe: Recipe, seed: int, out: str | os.PathLike, backend: str = "gl", fsync: bool = False):
        from .render import make_renderer
        from .textures import build_bank

        self.recipe, self.seed, self.fsync = recipe, int(seed), fsync
        self.root = RackLayRoot(out)
        self.grid = L.Grid(recipe.layout_size, recipe.extent_m)
        self.bank = build_bank(recipe.texture_family, self.seed, recipe.texture_dir)
        msaa = recipe.antialias if recipe.antialias >= 2 else 0
        self.pad = render_padding(recipe)
        self.renderer = make_renderer(self.bank, recipe.image_width + 2 * self.pad[0],
                                      recipe.image_height + 2 * self.pad[1], msaa=msaa, backend=backend)

    def close(self):
        self.renderer.release()

    def make(self, index: int):
        """Everything of one sample in memory: (scene, rgb, maps, top, front, meta, kitti, timings)."""
        from .effects import apply_distortion, distortion_maps, edge_antialias, photometric
        from .groundtruth import kitti_lines, object_annotations, scene_layouts, scene_meta
        from .scene import Camera, sample_scene

        r = self.recipe
        t0, c0 = time.perf_counter(), time.process_time()
        scene = sample_scene(r, self.seed, index)
        t1, c1 = time.perf_counter(), time.process_time()
        cam = scene.camera
        px, py = self.pad
        rcam = None
        if px or py:
            K = cam.K.copy()
            K[0, 2] += px
            K[1, 2] += py
            rcam = Camera(K=K, R=cam.R, t=cam.t, width=cam.width + 2 * px, height=cam.height + 2 * py)
        maps = distortion_maps(cam.K, cam.k1, cam.width, cam.height, offset=(px, py)) if cam.k1 else None
        region = (px, py, px + cam.width, py + cam.height) if maps is None else \
            source_region(maps, (cam.width + 2 * px, cam.height + 2 * py))
        out = self.renderer.render(scene, rcam, region=region)
        t2, c2 = time.perf_counter(), time.process_time()
        rgb, inst, depth, normals = out.rgb, out.instance, out.depth, out.normals
        if r.antialias == 1:
            rgb = edge_antialias(rgb, inst)
        if maps is not None:
            maps = (maps[0] - np.float32(region[0]), maps[1] - np.float32(region[1]))
            rgb, (inst, depth, normals) = apply_distortion(maps, rgb, [inst, depth, normals])
        rgb = photometric(rgb, scene.effects)
        top, front = scene_layouts(scene, self.grid, r.R)
        objects = object_annotations(scene, inst, coco=r.write_coco)
        meta = scene_meta(scene, r, self.grid, objects)
        kitti = kitti_lines(objects) if r.write_kitti else None
        t3, c3 = time.perf_counter(), time.process_time()
        maps = {"instance": inst, "depth": depth, "normals": normals}
        times = {"sample": t1 - t0, "render": t2 - t1, "groundtruth": t3 - t2,
                 "cpu_sample": c1 - c0, "cpu_render": c2 - c1, "cpu_groundtruth": c3 - c2}
        return scene, rgb, maps, top, front, meta, kitti, times

    def generate(self, index: int) -> dict:
        """Make and write one sample (meta last: it marks the index finished); returns per-stage seconds."""
        from .groundtruth import depth_png, semantic_map

        scene, rgb, maps, top, front, meta, kitti, t = self.make(index)
        r, root, sid, fs = self.recipe, self.root.root, sample_id(index), self.fsync
        t0, c0 = time.perf_counter(), time.process_time()
        if r.write_depth:
            atomic_write_bytes(extra_path(root, "depth", sid), encode_png(depth_png(maps["depth"]), "up"), fsync=fs)
        if r.write_normals:
            atomic_write_bytes(extra_path(root, "normals", sid), encode_png(maps["normals"], "up"), fsync=fs)
        if r.write_semantic:
            atomic_write_bytes(extra_path(root, "semantic", sid), encode_png(semantic_map(scene, maps["instance"]), "up"), fsync=fs)
        if r.write_instance:
            atomic_write_bytes(extra_path(root, "instance", sid), encode_png(maps["instance"].astype(np.uint16), "up"), fsync=fs)
        if kitti is not None:
            atomic_write_text(extra_path(root, "kitti", sid), kitti, fsync=fs)
        for view, arr in (("top", top), ("front", front)):
            atomic_save_npy(self.root.layout_path(view, sid), L.encode(arr), fsync=fs)
        atomic_write_bytes(self.root.image_path(sid), encode_png(rgb, "sub"), fsync=fs)
        atomic_write_json(self.root.meta_path(sid), meta, indent=None, fsync=fs)
        t["write"] = time.perf_counter() - t0
        t["cpu_write"] = time.process_time() - c0
        return t


# --- multiprocessing ---------------------------------------------------------------------
#: llvmpipe threads (LP_NUM_THREADS) of each worker when there are several: 0 rasterises in the
#: worker's own thread, which with one worker per core costs ~15 % less CPU per render than
#: handing each frame to a rasteriser thread (1)
WORKER_LP_THREADS = 0
_WORKER: Generator | None = None


def lp_threads_for(lp_threads: int | None, workers: int) -> int | None:
    """The LP_NUM_THREADS a run sets: `lp_threads` when given, else WORKER_LP_THREADS with
    several workers, else None (llvmpipe's default, or the caller's environment)."""
    if lp_threads is not None:
        return lp_threads
    return WORKER_LP_THREADS if workers > 1 else None


def _init_worker(recipe_dict, seed, out, lp_threads, fsync):
    global _WORKER
    if lp_threads is not None:
        os.environ["LP_NUM_THREADS"] = str(lp_threads)
    _WORKER = Generator(recipe_from_dict(recipe_dict, "recipe"), seed, out, fsync=fsync)


def _work(index):
    return index, _WORKER.generate(index)


def is_done(root: RackLayRoot, index: int, recipe: Recipe) -> bool:
    sid = sample_id(index)
    if not root.meta_path(sid).exists():
        return False
    return root.image_path(sid).exists() and root.layout_path("top", sid).exists() and \
        root.layout_path("front", sid).exists()


def generator_fingerprint() -> str:
    """A short hash of the code that decides what a seed renders (racklay/synth/*.py and the
    layout convention). Same seed + same recipe gives the same files only under the same
    fingerprint; the manifest records it so a dataset is never resumed by different code."""
    import hashlib

    h = hashlib.sha256()
    here = Path(__file__).resolve().parent
    for f in sorted(here.glob("*.py")) + [here.parent / "layout.py"]:
        h.update(f.name.encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


def check_manifest(out: Path, recipe: Recipe, n: int, seed: int) -> dict:
    """Write out/waresynth.json, or check that an existing one describes the same dataset."""
    from .. import __version__

    man = {"generator": "racklay synth (WareSynth)", "version": __version__, "code": generator_fingerprint(),
           "recipe": recipe.to_dict(), "n": int(n), "seed": int(seed)}
    p = out / MANIFEST
    if p.exists():
        try:
            old = json.loads(p.read_text())
        except json.JSONDecodeError:
            raise ValueError(f"{p}: invalid JSON; remove it or use another --out") from None
        diffs = [k for k in ("n", "seed") if old.get(k) != man[k]]
        diffs += [f"recipe.{k}" for k in man["recipe"] if old.get("recipe", {}).get(k) != man["recipe"][k]]
        if diffs:
            raise ValueError(f"{p}: {out} holds a dataset made with different settings ({', '.join(diffs[:5])}); "
                             f"use another --out or the same recipe/--n/--seed to resume")
        if "code" in old and old["code"] != man["code"]:
            raise ValueError(f"{p}: {out} was made by a different generator version (code {old['code']}, "
                             f"this one {man['code']}): its scenes would not match; finish it with that "
                             f"version or use another --out")
    else:
        stray = next((f for f in out.rglob("*") if f.is_file()), None) if out.is_dir() else None
        if stray is not None:
            raise ValueError(f"{out}: folder holds files not made by racklay synth (e.g. {stray}) and no "
                             f"{MANIFEST}; use an empty or new --out")
        atomic_write_json(p, man)
    return man


@dataclass
class RunResult:
    out: Path
    generated: list = field(default_factory=list)
    skipped: int = 0
    timings: dict = field(default_factory=lambda: {s: 0.0 for s in STAGES})
    wall: float = 0.0
    splits: dict = field(default_factory=dict)


def generate_dataset(recipe: Recipe, n: int, out: str | os.PathLike, seed: int = 0, shard: str | None = None,
                     workers: int = 1, progress: bool = True, lp_threads: int | None = None,
                     limit: int | None = None, finalize: bool = True, fsync: bool = False) -> RunResult:
    """Generate indices [0, n) of this shard into `out` (resuming), then write splits/COCO."""
    if n < 1:
        raise ValueError(f"--n must be >= 1, got {n}")
    si, sn = parse_shard(shard)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    check_manifest(out, recipe, n, seed)
    root = RackLayRoot(out)
    todo_all = [i for i in range(si, n, sn)]
    todo = [i for i in todo_all if not is_done(root, i, recipe)]
    res = RunResult(out=out, skipped=len(todo_all) - len(todo))
    if limit is not None:
        todo = todo[:limit]
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(todo_all), initial=res.skipped, desc=f"synth {recipe.name}", unit="img", dynamic_ncols=True)
    t0 = time.perf_counter()
    try:
        if workers <= 1:
            if lp_threads is not None:
                os.environ["LP_NUM_THREADS"] = str(lp_threads)
            gen = Generator(recipe, seed, out, fsync=fsync) if todo else None
            try:
                for i in todo:
                    t = gen.generate(i)
                    _acc(res, i, t, bar)
            finally:
                if gen:
                    gen.close()
        elif todo:
            lp = lp_threads_for(lp_threads, workers)
            for i, t in _pool_results(todo, workers, (recipe.to_dict(), seed, str(out), lp, fsync), out):
                _acc(res, i, t, bar)
    finally:
        res.wall = time.perf_counter() - t0
        if bar:
            bar.close()
        if finalize:
            res.splits = finalize_dataset(out, recipe, n, seed)
    return res


class WorkerCrash(RuntimeError):
    """A worker process died (killed, out of memory, a crash in the GL driver) before finishing
    its image. What was finished is on disk; running the same command again resumes."""


def _pool_results(todo: list[int], workers: int, initargs: tuple, out: Path):
    """(index, timings) of each index of `todo` as `workers` spawned processes finish them, a few
    in flight per worker. A worker that dies raises WorkerCrash naming the image (a plain
    multiprocessing pool would wait for its result for ever)."""
    import itertools
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    def crash(i: int) -> WorkerCrash:
        return WorkerCrash(f"{out}: a worker process died while making image {sample_id(i)} (killed, out of "
                           f"memory, or a crash in the GL driver); the finished images are kept: run the same "
                           f"command again to resume")

    queue = iter(todo)
    ex = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_init_worker, initargs=initargs)
    try:
        running = {ex.submit(_work, i): i for i in itertools.islice(queue, 2 * workers)}
        while running:
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in done:
                i = running.pop(f)
                try:
                    yield f.result()
                except BrokenProcessPool:
                    raise crash(i) from None
                nxt = next(queue, None)
                if nxt is not None:
                    try:
                        running[ex.submit(_work, nxt)] = nxt
                    except BrokenProcessPool:   # a worker died after this image finished: name one in flight
                        raise crash(min(running.values(), default=nxt)) from None
    finally:   # on an error or a stop (Ctrl-C, SIGTERM) the images being made finish, the rest never start
        ex.shutdown(wait=True, cancel_futures=True)


def _acc(res: RunResult, i, t, bar):
    res.generated.append(i)
    for k, v in t.items():
        res.timings[k] = res.timings.get(k, 0.0) + v
    if bar:
        bar.update(1)


def finalize_dataset(out: str | os.PathLike, recipe: Recipe, n: int, seed: int) -> dict:
    """Split files over the finished samples (assignment fixed by seed over all n indices, so
    every shard and the merged folder agree) and COCO instance files per split."""
    root = RackLayRoot(out)
    present = {p.stem for p in (root.root / "meta").glob("*.json") if not p.name.startswith(".")}
    all_ids = [sample_id(i) for i in range(n)]
    assignment = make_splits(all_ids, recipe.splits, seed)
    counts = {}
    for name, ids in assignment.items():
        ids = [s for s in ids if s in present and root.image_path(s).exists()]
        root.write_split(name, ids)
        counts[name] = len(ids)
        if recipe.write_coco:
            write_coco(root, name, ids, recipe.name)
    return counts


def write_coco(root: RackLayRoot, split: str, ids: list[str], recipe_name: str = "") -> Path:
    """annotations/instances_SPLIT.json (COCO instances: cartons and crates, polygons)."""
    from .scene import CATEGORY_NAMES

    images, anns = [], []
    for k, sid in enumerate(ids):
        meta = root.read_meta(sid)
        W, H = meta["image_size"]
        images.append({"id": int(sid), "file_name": f"Images/{sid}.png", "width": W, "height": H})
        for o in meta["objects"]:
            if not o.get("bbox_visible") or not o.get("segmentation"):
                continue
            x0, y0, x1, y1 = o["bbox_visible"]
            anns.append({"id": len(anns) + 1, "image_id": int(sid), "category_id": o["category_id"],
                         "bbox": [x0, y0, x1 - x0, y1 - y0], "area": o["visible_pixels"], "iscrowd": 0,
                         "segmentation": o["segmentation"],
                         "attributes": {"shelf_channel": o["channel"], "visible_fraction": o["visible_fraction"]}})
    coco = {"info": {"description": f"WareSynth recipe {recipe_name}, split {split}"},
            "categories": [{"id": i + 1, "name": n, "supercategory": n.split("_")[0] if n.startswith(("crate", "pallet")) else "carton"}
                           for i, n in enumerate(CATEGORY_NAMES)],
            "images": images, "annotations": anns}
    return atomic_write_json(root.root / "annotations" / f"instances_{split}.json", coco, indent=None)


# --- relayout ----------------------------------------------------------------------------
#: recipe keys that change what the layouts draw and nothing else (no random draw depends on them)
LAYOUT_KEYS = ("layout_extent", "layout_size", "extent_m")


class RelayoutError(ValueError):
    """A set that cannot be redrawn; the message names the file and the problem."""


def _link_or_copy(src: Path, dst: Path) -> None:
    """dst as a hard link to src (the same file, no extra disk), or a copy where the file system
    cannot link; through a temporary name, so dst is never half there."""
    import shutil
    import tempfile

    dst.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dst.name}.", suffix=".tmp", dir=dst.parent)
    os.close(fd)
    try:
        os.unlink(tmp)
        try:
            os.link(src, tmp)
        except OSError:
            shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
    except BaseException:
        if os.path.lexists(tmp):
            os.unlink(tmp)
        raise


def _scene_matches(scene, meta: dict) -> str | None:
    """None if the scene sampled now is the one the meta describes (camera and every object's
    centre and size, to the meta's rounding); else what differs."""
    from .scene import Camera

    cam = Camera.from_meta(meta)
    for key in ("K", "R", "t"):
        if np.abs(getattr(cam, key) - np.asarray(getattr(scene.camera, key), float)).max() > 1e-5:
            return f"camera {key}"
    objs = meta.get("objects", [])
    for a in objs:
        o = scene.objects[a["id"] - 1] if 0 < a["id"] <= len(scene.objects) else None
        if o is None or np.abs(np.asarray(a["center_world"]) - np.asarray(o.center)).max() > 1e-4 or \
                np.abs(np.asarray(a["size"]) - np.asarray(o.size)).max() > 1e-4:
            return f"object {a['id']}"
    return None


def relayout_dataset(src: str | os.PathLike, out: str | os.PathLike, overrides: list[str] | dict,
                     progress: bool = True) -> RunResult:
    """A copy of the WareSynth set `src` in `out` whose layouts are redrawn under other layout
    keys (LAYOUT_KEYS: layout_extent, layout_size, extent_m), without rendering: each scene is
    sampled again from its (recipe, seed, index), checked against its meta (camera and every
    object), and its layouts and meta written anew; the image and the per-pixel maps are the
    source's files (hard links where the file system allows, else copies). Resumes like
    generate_dataset; splits and COCO files are rebuilt at the end."""
    from ..atomic import atomic_write_json
    from ..data import LEVEL_SPANS_KEY
    from .groundtruth import grid_meta, layout_meta, level_spans, scene_layouts
    from .recipe import RecipeError, parse_override
    from .scene import sample_scene

    src, out = Path(src), Path(out)
    man_path = src / MANIFEST
    if not man_path.is_file():
        raise RelayoutError(f"{src}: not a WareSynth set (no {MANIFEST}); --relayout takes a folder written by racklay synth")
    try:
        man = json.loads(man_path.read_text())
        n, seed, base = int(man["n"]), int(man["seed"]), dict(man["recipe"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError):
        raise RelayoutError(f"{man_path}: not a readable WareSynth manifest (n, seed, recipe)") from None
    if src.resolve() == out.resolve():
        raise RelayoutError(f"{out}: --out is the source set itself; relayout writes a new folder")
    items = overrides.items() if isinstance(overrides, dict) else [parse_override(o) for o in overrides]
    changed = {k: v for k, v in items}
    other = sorted(set(changed) - set(LAYOUT_KEYS))
    if other:
        raise RecipeError(f"--set {', '.join(other)}: a relayout can change only {', '.join(LAYOUT_KEYS)} "
                          f"(the other keys change the images: render a new set with racklay synth)")
    recipe = recipe_from_dict({**base, **changed}, f"{man_path} with --set overrides")
    if not changed or all(base.get(k) == getattr(recipe, k) for k in changed):
        raise RecipeError(f"--set: give a layout key to change ({', '.join(LAYOUT_KEYS)}); as given the layouts "
                          f"would be {src}'s")
    out.mkdir(parents=True, exist_ok=True)
    out_man = check_manifest(out, recipe, n, seed)
    if (out / MANIFEST).is_file() and "relayout_of" not in json.loads((out / MANIFEST).read_text()):
        # the images are the source's, rendered by its code
        atomic_write_json(out / MANIFEST, {**out_man, "relayout_of": {"path": str(src.resolve()),
                                                                      "code": man.get("code")}})
    s_root, o_root = RackLayRoot(src), RackLayRoot(out)
    have = sorted(i for i in range(n) if s_root.meta_path(sample_id(i)).is_file())
    todo = [i for i in have if not is_done(o_root, i, recipe)]
    res = RunResult(out=out, skipped=len(have) - len(todo))
    grid = L.Grid(recipe.layout_size, recipe.extent_m)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(have), initial=res.skipped, desc=f"relayout {recipe.layout_extent}", unit="img",
                   dynamic_ncols=True)
    t0 = time.perf_counter()
    try:
        for i in todo:
            sid = sample_id(i)
            meta_file = s_root.meta_path(sid)
            meta = s_root.read_meta(sid)
            scene = sample_scene(recipe, seed, i)
            try:
                diff = _scene_matches(scene, meta)
            except (KeyError, TypeError, ValueError, IndexError):
                raise RelayoutError(f"{meta_file}: not a WareSynth meta (no readable camera and objects)") from None
            if diff:
                raise RelayoutError(f"{meta_file}: the scene sampled now differs from the one rendered ({diff}): "
                                    f"{src} was made by generator code {man.get('code', '?')}, which samples scenes "
                                    f"differently from this version ({generator_fingerprint()}); render it anew")
            image = s_root.image_path(sid)
            if not image.is_file():
                raise RelayoutError(f"{image}: missing (its meta is there); the source set is incomplete")
            _link_or_copy(image, o_root.root / image.relative_to(src))
            for kind in EXTRA_FILES:
                f = extra_path(src, kind, sid)
                if f.is_file():
                    _link_or_copy(f, extra_path(out, kind, sid))
            top, front = scene_layouts(scene, grid, recipe.R)
            for view, arr in (("top", top), ("front", front)):
                atomic_save_npy(o_root.layout_path(view, sid), L.encode(arr), fsync=False)
            meta["rack"].update(layout_meta(scene))
            meta["grid"] = grid_meta(grid, recipe)
            meta[LEVEL_SPANS_KEY] = level_spans(scene)      # they follow what the layouts draw
            atomic_write_json(o_root.meta_path(sid), meta, indent=None, fsync=False)   # last: marks it finished
            res.generated.append(i)
            if bar:
                bar.update(1)
    finally:
        res.wall = time.perf_counter() - t0
        if bar:
            bar.close()
        res.splits = finalize_dataset(out, recipe, n, seed)
    return res
