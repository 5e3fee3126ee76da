"""Export a project as a RackLay-format dataset, and import one for review.

Export computes each image's layouts with annotate.geometry (which draws through
racklay.layout) and writes them with racklay.data.RackLayRoot, so the result is exactly what
`racklay check-data` and the training code read. Both directions check everything first (every
annotation and photo on export; every photo and layout file on import) and stop at the first bad
file with a message naming it, before anything is written. Export then builds the dataset in a
hidden folder beside --out and renames it into place; import removes what it wrote if a write
fails. Either way a failed run leaves nothing half-written.
"""
from __future__ import annotations

import math
import os
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from racklay import layout as L
from racklay.atomic import encode_png
from racklay.data import DataError, RackLayRoot, check_split_name, make_splits

from . import geometry as G
from . import schema as S
from .store import DONE_STATUSES, Project, StoreError, photo_info


def parse_counts(text: str, what: str = "--split") -> dict[str, float]:
    """'train=442,test=100' -> {'train': 442.0, 'test': 100.0}."""
    out: dict[str, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, eq, val = part.partition("=")
        try:
            if not eq or not name.strip():
                raise ValueError
            out[name.strip()] = float(val)
            if not math.isfinite(out[name.strip()]):
                raise ValueError
        except ValueError:
            raise ValueError(f"{what}: cannot read {part!r} (expected name=value, e.g. train=0.8)") from None
        if out[name.strip()] < 0:
            raise ValueError(f"{what}: {part!r} is negative")
    if not out:
        raise ValueError(f"{what}: no splits given")
    return out


def check_fractions(fractions: dict[str, float], what: str = "--split-fractions") -> None:
    """Split fractions must cover every exported image: they sum to 1 (within 1e-6)."""
    total = sum(fractions.values())
    if abs(total - 1) > 1e-6:
        given = ",".join(f"{k}={v:g}" for k, v in fractions.items())
        raise ValueError(f"{what}: the fractions must sum to 1, but {given} sum to {total:.6g}")


#: the split of a project's SOURCES.tsv that holds sites kept apart from every training run: scored
#: for release decisions only, never trained on (docs/real-dataset.md, "Holdout")
HOLDOUT_SPLIT = "holdout"


def read_split_file(path: str | os.PathLike) -> dict[str, str]:
    """photo file name -> split name, from a tab-separated file with a header row naming a `file`
    and a `split` column (e.g. a project's SOURCES.tsv with a split chosen by site). Strict: a
    missing column, an empty split or a photo listed twice is an error naming the file and line."""
    import csv

    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:    # a spreadsheet's byte-order mark too
            reader = csv.DictReader(f, delimiter="\t")
            cols = reader.fieldnames or []
            missing = [c for c in ("file", "split") if c not in cols]
            if missing:
                raise ValueError(f"{path}: no {' and no '.join(repr(c) for c in missing)} column in the header "
                                 f"(columns: {', '.join(cols) or 'none'})")
            out: dict[str, str] = {}
            for line, row in enumerate(reader, start=2):
                name, split = (row.get("file") or "").strip(), (row.get("split") or "").strip()
                if not name or not split:
                    raise ValueError(f"{path}: line {line}: empty {'file' if not name else 'split'}")
                if name in out:
                    raise ValueError(f"{path}: line {line}: {name} is listed twice")
                try:
                    check_split_name(split)
                except ValueError as e:
                    raise ValueError(f"{path}: line {line}: {e}") from None
                out[name] = split
    except OSError as e:
        raise ValueError(f"{path}: cannot read the split file ({e.strerror or e})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a UTF-8 text file") from None
    if not out:
        raise ValueError(f"{path}: lists no photo")
    return out


def split_ids(ids: list[str], counts: dict[str, float] | None = None,
              fractions: dict[str, float] | None = None, seed: int = 0) -> dict[str, list[str]]:
    """Reproducible splits by exact counts or by fractions (default train=0.8,test=0.2): the
    command line's values checked with messages naming its flags, then cut by
    racklay.data.make_splits (the one shuffle-and-cut of the toolkit)."""
    if counts is not None:
        if any(c != int(c) for c in counts.values()):
            raise ValueError(f"--split: counts must be whole numbers, got {counts}")
        need = int(sum(counts.values()))
        if need > len(ids):
            raise ValueError(f"--split asks for {need} images but {len(ids)} are exported")
        if need < len(ids):   # the rest would be in no split: written, but never trained or tested on
            raise ValueError(f"--split gives a split to {need} of the {len(ids)} exported images; the counts "
                             f"must add up to {len(ids)} (or use --split-fractions)")
        return make_splits(ids, counts={k: int(v) for k, v in counts.items()}, seed=seed)
    fractions = fractions or {"train": 0.8, "test": 0.2}
    check_fractions(fractions)
    return make_splits(ids, fractions, seed)


def annotation_layouts(project: Project, ann: dict) -> tuple[np.ndarray, np.ndarray, G.Scene]:
    scene = G.build_scene(ann, project.settings)
    if not scene.shelf_v:
        raise G.GeometryError("no shelf marked")
    return (*scene_layouts(project, scene), scene)


def scene_layouts(project: Project, scene: G.Scene) -> tuple[np.ndarray, np.ndarray]:
    """(top, front) layouts of a built scene at the project's R and grid."""
    st = project.settings
    return scene.layouts(st["R"], L.Grid(st["D"], st["extent"]))


def _dir_mode() -> int:
    """The mode a plain mkdir gives a folder (0777 minus the umask); mkdtemp makes 0700 ones."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o777 & ~mask


@contextmanager
def staged_folder(out: Path):
    """A hidden temporary folder beside `out` (with a plain mkdir's mode) to write into; renamed
    to `out` (absent or an empty folder) when the block ends, removed if it fails, so `out` is
    never half-written."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:
        os.chmod(tmp, _dir_mode())
        yield tmp
        os.rename(tmp, out)  # atomic; replaces `out` only if it is an empty folder
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def parse_statuses(text: str) -> tuple[str, ...]:
    """--only-status's comma-separated list, 'done, approved' -> ('done', 'approved') (an argparse
    `type`; `check_statuses` checks the names where they are used)."""
    return tuple(s.strip() for s in text.split(",") if s.strip())


def check_statuses(only_status) -> None:
    """Every status asked for is one the annotation format knows (an --only-status error)."""
    bad = [s for s in only_status if s not in S.STATUSES]
    if bad:
        raise ValueError(f"--only-status: unknown status {bad[0]!r} (statuses: {', '.join(S.STATUSES)})")


def _sample_meta(project: Project, name: str, ann: dict, scene: G.Scene) -> dict:
    aspect = S.pixel_aspect(project.settings)
    return {"source": "annotate", "source_image": name, "annotation_version": ann["version"],
            "status": ann["status"], "rack": {k: ann["rack"][k] for k in ("width", "height", "depth", "preset")},
            "shelf_heights_m": [round(v, 4) for v in scene.shelf_v],
            "clear_heights_m": [round(v, 4) for v in scene.clear],
            "level_spans": [[round(x, 4) for x in span] for span in scene.level_spans(ann["image_size"][0])],
            "boxes": [{"id": b.id, "shelf": b.shelf, "x0": round(L.u_to_x(b.u0, scene.width), 4),
                       "x1": round(L.u_to_x(b.u1, scene.width), 4), "z0": round(b.z0, 4),
                       "height": round(b.v1 - b.v0, 4), "depth": round(b.depth, 4),
                       "front_offset": round(b.front_offset, 4)} for b in scene.boxes],
            "grid": {"D": project.settings["D"], "extent": project.settings["extent"]},
            **({"pixel_aspect": aspect} if aspect != 1 else {}),
            "warnings": scene.warnings}


def export_project(project: Project, out: str | os.PathLike, counts=None, fractions=None, seed: int = 0,
                   only_status=DONE_STATUSES, progress: bool = False, skip_invalid: bool = False,
                   split_of: dict[str, str] | None = None) -> dict:
    """Write every annotation whose status is in `only_status` as a RackLay sample. Returns a
    summary dict. Refuses a non-empty output folder. `split_of` (photo name -> split, see
    read_split_file) fixes each photo's split instead of a shuffle: every exported photo must be
    in it, and every photo it names must be in the project.

    Every annotation, its layouts and its photo are checked before anything is written: the photo
    must be readable, and the annotation must fit it (schema.photo_problems: same name and size,
    every point inside it, no box without area) and give layouts (annotate.geometry); an annotation
    file that cannot be read (truncated, invalid JSON or schema) is a problem like the others. Any
    problem stops the export with one line naming every bad file, or, with `skip_invalid`, those
    annotations are left out and listed in the summary's "skipped". The geometry's warnings for the exported photos (which
    also go into meta/*.json) are in its "warnings". The dataset is then built in a hidden
    temporary folder beside `out` and renamed to `out` at the end, so a failure (or a kill) never
    leaves a half-written dataset at `out`."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: is a file, expected a folder")
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"{out}: output folder is not empty; choose a new folder")
    check_statuses(only_status)
    if fractions is not None:
        check_fractions(fractions)
    if split_of is not None:
        stray = sorted(set(split_of) - set(project.images()))
        if stray:
            raise ValueError(f"the split file names {len(stray)} photo(s) that are not in {project.root} "
                             f"(first: {stray[0]})")
    chosen, other_status, unannotated = [], {}, 0
    skipped: list[tuple[str, str]] = []
    warnings: list[str] = []
    for name in project.images():
        p = project.annotation_path(name)
        try:
            ann = project.read_annotation(name)  # a truncated or invalid file names itself
        except ValueError as e:
            skipped.append((str(p), str(e)))
            continue
        if ann is None:
            unannotated += 1
            continue
        if ann["status"] not in only_status:
            other_status[ann["status"]] = other_status.get(ann["status"], 0) + 1
            continue
        try:
            w, h = project.image_size(name)  # the photo's header first: a bad photo or a bomb names itself
            problems = S.photo_problems(ann, w, h, name)
            if problems:
                more = f"; and {len(problems) - 1} more" if len(problems) > 1 else ""
                raise ValueError(f"{p}: cannot export ({problems[0]}{more})")
            try:
                scene = annotation_layouts(project, ann)[2]
            except (G.GeometryError, ValueError) as e:
                raise ValueError(f"{p}: cannot export ({e})") from None
            project.read_image(name)  # an unreadable photo stops the export, naming itself
        except ValueError as e:       # StoreError, DataError, SchemaError: one line naming the file
            skipped.append((str(p), str(e)))
            continue
        warnings += [f"{name}: {msg}" for msg in scene.warnings]
        chosen.append((name, ann, scene))   # the scene is kept (small); layouts are drawn when written
    if skipped and not skip_invalid:
        if len(skipped) == 1:
            raise ValueError(skipped[0][1])
        raise ValueError(f"{len(skipped)} annotations cannot be exported (--skip-invalid exports the rest): "
                         + " | ".join(msg for _, msg in skipped))
    if not chosen:
        why = f" ({len(skipped)} invalid, first: {skipped[0][1]})" if skipped else ""
        raise ValueError(f"{project.root}: no annotation with status {', '.join(only_status)} to export{why}")
    sids = [f"{k:06d}" for k in range(len(chosen))]
    if split_of is not None:
        unsplit = [name for name, _, _ in chosen if name not in split_of]
        if unsplit:
            raise ValueError(f"the split file gives no split for {len(unsplit)} exported photo(s) "
                             f"(first: {unsplit[0]})")
        splits: dict[str, list[str]] = {}
        for sid, (name, _, _) in zip(sids, chosen):
            splits.setdefault(split_of[name], []).append(sid)
    else:
        splits = split_ids(sids, counts, fractions, seed)
    # everything checked: build the dataset beside `out`, then rename it into place
    with staged_folder(out) as tmp:
        ds = RackLayRoot(tmp)
        it = zip(sids, chosen)
        if progress:
            from tqdm import tqdm
            it = tqdm(list(it), desc="export", unit="img")
        for sid, (name, ann, scene) in it:
            top, front = scene_layouts(project, scene)
            # a photo stored squeezed is written as taken (the project's pixel_aspect), so that a
            # model trained on the set sees real proportions; the layouts are metric either way
            image = G.restore_aspect(project.read_image(name), S.pixel_aspect(project.settings))
            ds.write_sample(sid, image_bytes=encode_png(image), top=top, front=front,
                            meta=_sample_meta(project, name, ann, scene))
        for split, ids in splits.items():
            ds.write_split(split, ids)
    # said, never silent: what was left out and why (annotations whose photo left the project
    # cannot be exported, but they are listed)
    return {"out": str(out), "images": len(chosen), "splits": {k: len(v) for k, v in splits.items()},
            "left_out": {"other_status": other_status, "unannotated": unannotated,
                         "no_photo": project.orphan_annotations()},
            "skipped": skipped, "warnings": warnings}


@dataclass
class ImportPlan:
    """A RackLay dataset checked for `annotate import`: every listed sample's photo decodes and
    every layout file decodes with the same (R, D)."""
    ds: RackLayRoot
    ids: list[str]
    views: tuple[str, ...]
    R: int
    D: int
    prefix: str

    def name(self, sid: str) -> str:
        return f"{self.prefix}_{sid}.png"


def check_import(root: str | os.PathLike, split: str | None = None) -> ImportPlan:
    """Read every sample `annotate import` would bring in and refuse the dataset at the first
    bad or missing file, naming it. Nothing is written."""
    ds = RackLayRoot(root)
    if not ds.root.is_dir():
        raise DataError(f"{ds.root}: dataset folder not found")
    ids = ds.resolve(split)
    views = ds.views()
    if not views:
        raise ValueError(f"{ds.root}: no topLayouts/ or frontLayouts/ folder")
    if split in (None, "all"):
        # a sample with layouts but no photo is refused below, never left out without a word
        ids = sorted(set(ids).union(*(ds.layout_ids(v) for v in views)))
    if not ids:
        raise ValueError(f"{ds.root}: no images to import")
    prefix = "".join(c if c.isalnum() or c in "-_" else "_" for c in ds.root.resolve().name) or "import"
    # the (R, D) most layout files have, so the file that differs is the one named
    ref = ds.layout_shape(ids, views)
    if ref is None:
        ds.read_layouts(views[0], ids[0])     # names the first file and what is wrong with it
        raise DataError(f"{ds.root}: no readable layout files")
    plan = ImportPlan(ds, list(ids), views, ref[0], ref[1], prefix)
    for sid in ids:
        if not ds.image_path(sid).is_file():
            missing = [str(ds.layout_path(v, sid)) for v in views if ds.layout_path(v, sid).is_file()]
            has = f" (the sample has layouts {', '.join(missing)})" if missing else ""
            raise DataError(f"{ds.image_path(sid)}: image file not found{has}")
        photo_info(ds.image_path(sid), str(ds.image_path(sid)))  # from the header: bombs cost nothing
        ds.read_image(sid)
        for view in views:
            ds.read_layouts(view, sid, R=plan.R, D=plan.D)
    return plan


def import_dataset(root: str | os.PathLike | ImportPlan, project: Project, split: str | None = None) -> list[str]:
    """Bring a RackLay dataset's images and layouts into a project for review: photos are copied
    (as DATASETNAME_ID.png), layouts into imported/, and each image gets status 'needs review'
    with its layouts attached read-only. Returns the image names added.

    `root` is a dataset folder or the ImportPlan of check_import(). Every sample and the project
    are checked before the first write; if a write fails, what was written is removed again."""
    plan = root if isinstance(root, ImportPlan) else check_import(root, split)
    ds, R, D = plan.ds, plan.R, plan.D
    st = project.settings
    # R and D must match the project's (a project without annotations adopts the dataset's)
    if (st["R"], st["D"]) != (R, D) and project.has_annotations():
        raise ValueError(f"{ds.root}: layouts are R={R}, D={D} but the project uses R={st['R']}, D={st['D']}")
    names = [plan.name(sid) for sid in plan.ids]
    for name in names:
        if project.image_path(name).exists() or project.annotation_path(name).exists():
            raise StoreError(f"{project.root / name}: already in the project (imported before?)")
    with project.all_or_nothing(names):  # a failed write removes what was written
        if (st["R"], st["D"]) != (R, D):  # an empty project adopts the dataset's R and D
            project.save_settings(dict(st, R=R, D=D))
        for sid, name in zip(plan.ids, names):
            imp = {"dataset": str(ds.root.resolve()), "id": sid, "top": None, "front": None}
            for view in plan.views:
                imp[view] = project.save_imported(name, view, ds.read_layouts(view, sid, R=R, D=D))
            image = ds.read_image(sid)
            project.add_image(name, encode_png(image))
            ann = S.new_annotation(name, image.shape[1], image.shape[0])
            ann["status"] = "needs review"
            ann["imported"] = imp
            project.save(ann, user="annotate import")
    return names
