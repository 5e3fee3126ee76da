"""Export a project as a RackLay-format dataset, and import one for review.

Export computes each image's layouts with annotate.geometry (which draws through
racklay.layout) and writes them with racklay.data.RackLayRoot, so the result is exactly what
`racklay check-data` and the training code read. Every annotation is checked before the first
file is written: a bad one stops the export with a message naming it.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from racklay import layout as L
from racklay.atomic import atomic_save_npy, encode_png
from racklay.data import RackLayRoot, make_splits

from . import geometry as G
from . import schema as S
from .store import ANN_DIR, IMPORT_DIR, Project, StoreError


def parse_counts(text: str, what: str = "--split") -> dict[str, float]:
    """'train=442,test=100' -> {'train': 442.0, 'test': 100.0}."""
    out: dict[str, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, eq, val = part.partition("=")
        try:
            if not eq or not name.strip():
                raise ValueError
            out[name.strip()] = float(val)
        except ValueError:
            raise ValueError(f"{what}: cannot read {part!r} (expected name=value, e.g. train=0.8)") from None
        if out[name.strip()] < 0:
            raise ValueError(f"{what}: {part!r} is negative")
    if not out:
        raise ValueError(f"{what}: no splits given")
    return out


def split_ids(ids: list[str], counts: dict[str, float] | None = None,
              fractions: dict[str, float] | None = None, seed: int = 0) -> dict[str, list[str]]:
    """Reproducible splits by exact counts or by fractions (racklay.data.make_splits)."""
    if counts is not None:
        need = int(sum(counts.values()))
        if any(c != int(c) for c in counts.values()):
            raise ValueError(f"--split: counts must be whole numbers, got {counts}")
        if need > len(ids):
            raise ValueError(f"--split asks for {need} images but {len(ids)} are exported")
        order = list(ids)
        np.random.default_rng(seed).shuffle(order)
        out, start = {}, 0
        for name, n in counts.items():
            out[name] = sorted(order[start:start + int(n)])
            start += int(n)
        return out
    return make_splits(ids, fractions or {"train": 0.8, "test": 0.2}, seed)


def annotation_layouts(project: Project, ann: dict) -> tuple[np.ndarray, np.ndarray, G.Scene]:
    st = project.settings
    scene = G.build_scene(ann, st)
    if not scene.shelf_v:
        raise G.GeometryError("no shelf marked")
    top, front = scene.layouts(st["R"], L.Grid(st["D"], st["extent"]))
    return top, front, scene


def export_project(project: Project, out: str | os.PathLike, counts=None, fractions=None, seed: int = 0,
                   only_status=("done", "approved"), progress: bool = False) -> dict:
    """Write every annotation whose status is in `only_status` as a RackLay sample. Returns a
    summary dict. Refuses a non-empty output folder."""
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"{out}: output folder is not empty; choose a new folder")
    bad = [s for s in only_status if s not in S.STATUSES]
    if bad:
        raise ValueError(f"--only-status: unknown status {bad[0]!r} (statuses: {', '.join(S.STATUSES)})")
    chosen = []
    for name in project.images():
        p = project.annotation_path(name)
        if not p.exists():
            continue
        ann = S.load_annotation(p)  # a bad file stops the export, naming itself
        if ann["status"] not in only_status:
            continue
        try:
            top, front, scene = annotation_layouts(project, ann)
        except (G.GeometryError, ValueError) as e:
            raise ValueError(f"{p}: cannot export ({e})") from None
        chosen.append((name, ann, scene))
    if not chosen:
        raise ValueError(f"{project.root}: no annotation with status {', '.join(only_status)} to export")
    sids = [f"{k:06d}" for k in range(len(chosen))]
    splits = split_ids(sids, counts, fractions, seed)  # checked before anything is written
    ds = RackLayRoot(out)
    it = zip(sids, chosen)
    if progress:
        from tqdm import tqdm
        it = tqdm(list(it), desc="export", unit="img")
    for sid, (name, ann, _) in it:
        top, front, scene = annotation_layouts(project, ann)
        image = project.read_image(name)
        meta = {"source": "annotate", "source_image": name, "annotation_version": ann["version"],
                "status": ann["status"], "rack": {k: ann["rack"][k] for k in ("width", "height", "depth", "preset")},
                "shelf_heights_m": [round(v, 4) for v in scene.shelf_v],
                "clear_heights_m": [round(v, 4) for v in scene.clear],
                "boxes": [{"id": b.id, "shelf": b.shelf, "x0": round(b.u0 - scene.width / 2, 4),
                           "x1": round(b.u1 - scene.width / 2, 4), "z0": round(b.z0, 4),
                           "height": round(b.v1 - b.v0, 4), "depth": round(b.depth, 4),
                           "front_offset": round(b.front_offset, 4)} for b in scene.boxes],
                "grid": {"D": project.settings["D"], "extent": project.settings["extent"]},
                "warnings": scene.warnings}
        ds.write_sample(sid, image_bytes=encode_png(image), top=top, front=front, meta=meta)
    for name, ids in splits.items():
        ds.write_split(name, ids)
    return {"out": str(out), "images": len(chosen), "splits": {k: len(v) for k, v in splits.items()}}


def import_dataset(root: str | os.PathLike, project: Project, split: str | None = None) -> list[str]:
    """Bring a RackLay dataset's images and layouts into a project for review: photos are copied
    (as DATASETNAME_ID.png), layouts into imported/, and each image gets status 'needs review'
    with its layouts attached read-only. Returns the image names added."""
    ds = RackLayRoot(root)
    ids = ds.resolve(split)
    if not ids:
        raise ValueError(f"{ds.root}: no images to import")
    prefix = "".join(c if c.isalnum() or c in "-_" else "_" for c in ds.root.resolve().name) or "import"
    views = ds.views()
    if not views:
        raise ValueError(f"{ds.root}: no topLayouts/ or frontLayouts/ folder")
    # R and D must match the project's (empty project: adopt the dataset's)
    first = ds.read_layouts(views[0], ids[0])
    R, D = first.shape[0], first.shape[-1]
    st = project.settings
    if (st["R"], st["D"]) != (R, D):
        if list((project.root / ANN_DIR).glob("*.json")) if (project.root / ANN_DIR).is_dir() else []:
            raise ValueError(f"{ds.root}: layouts are R={R}, D={D} but the project uses R={st['R']}, D={st['D']}")
        project.save_settings(dict(st, R=R, D=D))
    added = []
    for sid in ids:
        name = f"{prefix}_{sid}.png"
        if project.image_path(name).exists():
            raise StoreError(f"{project.root / name}: already in the project (imported before?)")
        image = ds.read_image(sid)
        imp = {"dataset": str(ds.root.resolve()), "id": sid, "top": None, "front": None}
        for view in views:
            arr = ds.read_layouts(view, sid, R=R, D=D)
            rel = f"{IMPORT_DIR}/{name}.{view}.npy"
            atomic_save_npy(project.project_file(rel), L.encode(arr))
            imp[view] = rel
        project.add_image(name, encode_png(image))
        ann = S.new_annotation(name, image.shape[1], image.shape[0])
        ann["status"] = "needs review"
        ann["imported"] = imp
        project.save(ann, user="annotate import")
        added.append(name)
    return added


def read_imported(project: Project, ann: dict) -> dict[str, np.ndarray]:
    """Class-id stacks of an annotation's imported layouts ({} when none)."""
    from racklay.data import read_layout_file

    imp = ann.get("imported") or {}
    out = {}
    for view in L.VIEWS:
        if imp.get(view):
            out[view] = read_layout_file(project.project_file(imp[view]))
    return out
