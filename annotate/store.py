"""The annotation project on disk: the only code that reads or writes a project folder.

    PROJECT_DIR/
      *.jpg | *.jpeg | *.png        the photos (top level; plain file names only)
      project.json                  settings: R, D, grid extent, rack presets (annotate.schema);
                                    saved like annotations (locked, version-checked)
      annotations/NAME.json         one annotation per photo (written on every action)
      annotations/.locks/NAME.lock  advisory locks held only while a save compares versions
      annotations/.history/NAME.json  undo/redo history of the image (so a reload keeps it)
      annotations/.history/.opened.json  the photo each user had open last
      imported/NAME.top.npy ...     read-only layouts brought in by `annotate import`

Every write is atomic (racklay.atomic: temp file + rename), so a killed server leaves each file
either at its previous or at its new state. Saves carry the version the labeller started from;
if the file on disk moved on meanwhile (another labeller, another tab), the save is refused with
a ConflictError that says who changed it, and nothing is overwritten. A file that fails
validation is never overwritten either: fix or delete it by hand.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import time
from pathlib import Path

import numpy as np

from racklay import layout as L
from racklay.atomic import atomic_save_npy, atomic_write_bytes, atomic_write_json

from . import schema as S

IMAGE_EXTS = (".jpg", ".jpeg", ".png")
SETTINGS_FILE = "project.json"
ANN_DIR = "annotations"
IMPORT_DIR = "imported"
LOCK_DIR = ".locks"
HISTORY_DIR = ".history"
#: undo (and redo) steps kept on disk per image
HISTORY_STEPS = 50
#: upload limit in bytes, and the longest side of a project photo; the pixel limit (width x
#: height) is racklay.data's, shared by every command (RACKLAY_MAX_MEGAPIXELS, default 40 Mpx)
MAX_UPLOAD_BYTES = 40 * 1024 * 1024
MAX_SIDE = 12_000
DONE_STATUSES = ("done", "approved")


class StoreError(ValueError):
    """A request the project cannot serve (bad name, outside the folder, bad upload)."""


class ConflictError(StoreError):
    """The annotation changed on disk since this labeller loaded it."""


class Project:
    """A project folder. Creates `project.json` with default settings when it is missing."""

    def __init__(self, root: str | os.PathLike, create: bool = True):
        self.root = Path(root).resolve()
        if not self.root.is_dir():
            if not create:
                raise StoreError(f"{self.root}: project folder not found")
            self.root.mkdir(parents=True)
        sp = self.root / SETTINGS_FILE
        if sp.exists():
            self.settings = S.load_settings(sp)
        elif create:
            self.settings = S.default_settings()
            atomic_write_json(sp, self.settings)
        else:
            raise StoreError(f"{sp}: project settings not found")

    # --- paths, all confined to the project folder ---
    def _inside(self, p: Path) -> Path:
        p = p.resolve()
        if p != self.root and self.root not in p.parents:
            raise StoreError(f"{p}: outside the project folder {self.root}")
        return p

    def image_path(self, name: str) -> Path:
        S.check_image_name(name, str(self.root))
        if Path(name).suffix.lower() not in IMAGE_EXTS:
            raise StoreError(f"{name}: not an image name ({', '.join(IMAGE_EXTS)})")
        return self._inside(self.root / name)

    def annotation_path(self, name: str) -> Path:
        S.check_image_name(name, str(self.root))
        return self._inside(self.root / ANN_DIR / f"{name}.json")

    def project_file(self, rel: str) -> Path:
        """A file of the project given by a relative path (imported layouts)."""
        return self._inside(self.root / rel)

    def images(self) -> list[str]:
        return sorted(p.name for p in self.root.iterdir()
                      if p.is_file() and p.suffix.lower() in IMAGE_EXTS and not p.name.startswith("."))

    # --- images ---
    def image_size(self, name: str) -> tuple[int, int]:
        """(width, height) from the photo's header, nothing decoded."""
        p = self.image_path(name)
        info = photo_info(p, str(p))
        return info.width, info.height

    def read_image(self, name: str) -> np.ndarray:
        """The photo as RGB pixels; refused from its header (one line naming the file) when it is
        not a PNG/JPEG within the limits, before anything is decoded."""
        from racklay.data import read_image

        p = self.image_path(name)
        photo_info(p, str(p))
        return read_image(p)

    def add_image(self, filename: str, data: bytes, overwrite: bool = False) -> str:
        """Store an uploaded photo after checking it is a real PNG/JPEG within the limits.
        Returns the stored file name (the upload's base name, sanitised)."""
        base = os.path.basename(str(filename).replace("\\", "/")).strip()
        base = "".join(c if c.isalnum() or c in "._-" else "_" for c in base).lstrip("._-") or "upload"
        fmt = check_image_bytes(data, base)
        stem, ext = os.path.splitext(base)
        ext = ext.lower()
        want = {"PNG": (".png",), "JPEG": (".jpg", ".jpeg")}[fmt]
        if ext not in want:
            ext = want[0]
        name = f"{stem[:100]}{ext}"
        path = self.image_path(name)
        if path.exists() and not overwrite:
            raise StoreError(f"{name}: an image of that name is already in the project")
        atomic_write_bytes(path, data)
        return name

    # --- annotations ---
    def load(self, name: str) -> dict:
        """The image's annotation (a fresh one if none was saved). SchemaError if the file is bad."""
        ann = self.read_annotation(name)
        if ann is None:
            w, h = self.image_size(name)
            return S.new_annotation(name, w, h)
        if ann["image"] != name:
            raise S.SchemaError(f"{self.annotation_path(name)}: field 'image': says {ann['image']!r}, expected {name!r}")
        return ann

    def read_annotation(self, name: str) -> S.Annotation | None:
        """The annotation saved for photo `name`, validated (SchemaError naming the file), or None
        when none was saved. Unlike load(), a file that names another photo is returned as it is
        (`annotate export` reports that with the photo's other problems)."""
        p = self.annotation_path(name)
        return S.load_annotation(p) if p.exists() else None

    def has_annotations(self) -> bool:
        """Whether any annotation file is in the project."""
        return any((self.root / ANN_DIR).glob("*.json"))

    def orphan_annotations(self) -> list[str]:
        """The annotation files whose photo is no longer in the project (paths, sorted)."""
        ann_dir = self.root / ANN_DIR
        if not ann_dir.is_dir():
            return []
        have = set(self.images())
        return sorted(str(q) for q in ann_dir.glob("*.json") if q.stem not in have)

    # --- layouts brought in by `annotate import` (read-only in the tool) ---
    def save_imported(self, name: str, view: str, classes: np.ndarray) -> str:
        """Write class-id layouts (R, D, D) of photo `name` as imported/NAME.VIEW.npy (RackLay file
        values, atomic); returns the path relative to the project, as the annotation stores it."""
        if view not in L.VIEWS:
            raise StoreError(f"{name}: unknown layout view {view!r} (views: {', '.join(L.VIEWS)})")
        rel = f"{IMPORT_DIR}/{name}.{view}.npy"
        atomic_save_npy(self.project_file(rel), L.encode(classes))
        return rel

    def read_imported(self, ann: S.Annotation) -> dict[str, np.ndarray]:
        """Class-id stacks of an annotation's imported layouts by view ({} when none)."""
        from racklay.data import read_layout_file

        imp = ann.get("imported") or {}
        return {view: read_layout_file(self.project_file(imp[view])) for view in L.VIEWS if imp.get(view)}

    @contextlib.contextmanager
    def all_or_nothing(self, names: list[str]):
        """For `annotate import`: if the block fails, whatever it wrote for the new photos `names`
        is removed again (the photo, its annotation, lock file and imported layouts), so are the
        project's folders that did not exist before it, and project.json is put back. The names
        must be new to the project (nothing of theirs is kept)."""
        folders = [self.root / ANN_DIR / LOCK_DIR, self.root / ANN_DIR, self.root / IMPORT_DIR]
        new_folders = [d for d in folders if not d.exists()]
        settings = self.settings
        try:
            yield
        except BaseException:
            for name in names:
                files = [self.image_path(name), self.annotation_path(name), self._lock_path(name)]
                files += [self.project_file(f"{IMPORT_DIR}/{name}.{view}.npy") for view in L.VIEWS]
                for f in files:
                    f.unlink(missing_ok=True)
            for d in new_folders:
                with contextlib.suppress(OSError):
                    d.rmdir()  # only if still empty
            if self.settings is not settings:
                self.restore_settings(settings)
            raise

    def disk_version(self, name: str) -> int:
        p = self.annotation_path(name)
        return S.load_annotation(p)["version"] if p.exists() else 0

    def _lock_path(self, name: str) -> Path:
        S.check_image_name(name, str(self.root))
        return self._inside(self.root / ANN_DIR / LOCK_DIR / f"{name}.lock")

    @contextlib.contextmanager
    def _lock(self, name: str):
        path = self._lock_path(name)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a+") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    def save(self, ann: dict, user: str | None = None) -> dict:
        """Save `ann`, which was edited starting from version ann['version']. Returns the saved
        annotation (version + 1). Raises ConflictError if the file moved on meanwhile, SchemaError
        if `ann` or the file on disk is invalid (the file is then left alone), StoreError if the
        photo is no longer in the project."""
        name = ann["image"]
        p = self.annotation_path(name)
        if not self.image_path(name).is_file():   # deleted while the server runs: refuse before writing
            raise StoreError(f"{name}: the photo is no longer in the project {self.root} (moved or deleted?); "
                             "not saved")
        new = dict(ann)
        with self._lock(name):
            on_disk = S.load_annotation(p) if p.exists() else None
            have = on_disk["version"] if on_disk else 0
            if have != ann["version"]:
                who = (on_disk or {}).get("updated_by") or "another session"
                raise ConflictError(
                    f"{name}: not saved - {who} changed this image meanwhile (version {have} on disk, "
                    f"your edit started from version {ann['version']}); reload the image to see their work")
            new["version"] = have + 1
            new["updated_by"] = user
            new["updated_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            S.validate_annotation(new, str(p))
            self._check_fits_photo(name, new, on_disk)
            atomic_write_json(p, new)
        return new

    def _check_fits_photo(self, name: str, new: dict, old: dict | None) -> None:
        """Refuse an edit that makes the annotation stop fitting its photo (schema.photo_problems:
        points outside the photo, boxes without area, wrong image_size). Problems the file on
        disk already had do not block saving, so a bad file can be fixed one item at a time."""
        w, h = self.image_size(name)
        before = set(S.photo_problems(old, w, h, name)) if old else set()
        fresh = [m for m in S.photo_problems(new, w, h, name) if m not in before]
        if fresh:
            more = f" (and {len(fresh) - 1} more)" if len(fresh) > 1 else ""
            raise S.SchemaError(f"{self.annotation_path(name)}: {fresh[0]}{more}")

    @contextlib.contextmanager
    def _settings_lock(self):
        """An advisory lock on the project folder itself (no lock file is left behind)."""
        fd = os.open(self.root, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    def save_settings(self, settings: dict, user: str | None = None) -> dict:
        """Save project.json like an annotation: under a lock, and only if the file on disk is
        still at the version `settings` started from (settings['version'], 0 for a file from
        before settings had versions); raises ConflictError otherwise, SchemaError if invalid.
        Returns (and keeps as self.settings) the saved settings, version + 1."""
        sp = self.root / SETTINGS_FILE
        S.validate_settings(settings, str(sp))
        with self._settings_lock():
            on_disk = S.load_settings(sp) if sp.exists() else None
            have = on_disk.get("version", 0) if on_disk else 0
            mine = settings.get("version", 0)
            if on_disk is not None and have != mine:
                raise ConflictError(
                    f"{sp}: not saved - the project settings changed meanwhile (version {have} on disk, "
                    f"your edit started from version {mine}); reload them and redo the change")
            new = dict(settings, version=have + 1)
            S.validate_settings(new, str(sp))
            atomic_write_json(sp, new)
        self.settings = new
        return new

    def restore_settings(self, old: dict) -> None:
        """Undo this object's last save_settings (a failed import): put `old` back exactly, if
        project.json is still the version that save wrote (else someone saved since: theirs stays)."""
        sp = self.root / SETTINGS_FILE
        with self._settings_lock():
            if S.load_settings(sp).get("version", 0) == self.settings.get("version", 0):
                atomic_write_json(sp, old)
                self.settings = old

    # --- undo history and the photo last opened (a reload continues where the labeller was) ---
    def _history_path(self, name: str) -> Path:
        S.check_image_name(name, str(self.root))
        return self._inside(self.root / ANN_DIR / HISTORY_DIR / f"{name}.json")

    def save_history(self, name: str, version: int, undo: list, redo: list) -> None:
        """Keep the image's undo and redo steps (annotations, newest last) for a reload; they
        belong to annotation version `version` and are dropped when the file moved on."""
        p = self._history_path(name)
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(p, {"version": int(version), "undo": undo[-HISTORY_STEPS:], "redo": redo[-HISTORY_STEPS:]})

    def load_history(self, name: str, version: int) -> tuple[list, list]:
        """(undo, redo) saved for annotation version `version`; empty when there is none, it is
        for another version (someone saved since) or it is unreadable (it is only a convenience,
        never ground truth: each step is validated like an annotation)."""
        p = self._history_path(name)
        try:
            h = S._read_json(p)
            if h.get("version") != version:
                return [], []
            for a in h["undo"] + h["redo"]:
                S.validate_annotation(a, str(p))
                if a["image"] != name:
                    return [], []
            return list(h["undo"]), list(h["redo"])
        except (OSError, S.SchemaError, KeyError, TypeError, AttributeError):
            return [], []

    def set_last_opened(self, name: str, user: str | None = None) -> None:
        p = self._inside(self.root / ANN_DIR / HISTORY_DIR / ".opened.json")
        p.parent.mkdir(parents=True, exist_ok=True)
        try:
            seen = S._read_json(p)
            seen = seen if isinstance(seen, dict) else {}
        except (OSError, S.SchemaError):
            seen = {}
        if seen.get(user or "") != name:
            atomic_write_json(p, {**{k: v for k, v in seen.items() if isinstance(v, str)}, user or "": name})

    def last_opened(self, user: str | None = None) -> str | None:
        try:
            seen = S._read_json(self.root / ANN_DIR / HISTORY_DIR / ".opened.json")
            name = seen.get(user or "") if isinstance(seen, dict) else None
        except (OSError, S.SchemaError):
            return None
        return name if isinstance(name, str) and name in self.images() else None

    def photo_problem(self, name: str) -> str | None:
        """Why a project photo cannot be used (one line naming it), or None. From the header only
        (racklay.data limits, PNG/JPEG, MAX_SIDE); cached by the file's size and time."""
        p = self.image_path(name)
        try:
            stt = p.stat()
        except OSError as e:
            return f"{name}: {e.strerror or 'unreadable'}"
        key = (stt.st_mtime_ns, stt.st_size, stt.st_ino)
        cache = self.__dict__.setdefault("_photo_cache", {})
        hit = cache.get(name)
        if hit and hit[0] == key:
            return hit[1]
        try:
            photo_info(p, name)
            why = None
        except StoreError as e:
            why = str(e)
        cache[name] = (key, why)
        return why

    def mark_unreadable(self, name: str, why: str) -> None:
        """Remember that a photo failed to decode although its header was fine (until it changes)."""
        p = self.image_path(name)
        with contextlib.suppress(OSError):
            stt = p.stat()
            self.__dict__.setdefault("_photo_cache", {})[name] = ((stt.st_mtime_ns, stt.st_size, stt.st_ino), why)

    # --- progress ---
    def statuses(self) -> dict[str, str]:
        """Status of every image ('todo' when never saved, 'invalid' when its file is bad,
        'unreadable' when the photo itself cannot be used). Files are re-read only when their
        modification time or size changed."""
        out = {}
        cache = self.__dict__.setdefault("_status_cache", {})
        for name in self.images():
            if self.photo_problem(name):
                out[name] = "unreadable"
                continue
            p = self.annotation_path(name)
            try:
                stt = p.stat()
            except FileNotFoundError:
                out[name] = "todo"
                continue
            key = (stt.st_mtime_ns, stt.st_size, stt.st_ino)
            hit = cache.get(name)
            if hit and hit[0] == key:
                out[name] = hit[1]
                continue
            try:
                out[name] = S.load_annotation(p)["status"]
            except S.SchemaError:
                out[name] = "invalid"
            cache[name] = (key, out[name])
        return out

    def progress(self) -> tuple[int, int]:
        """(n done or approved, N images)."""
        st = self.statuses()
        return sum(s in DONE_STATUSES for s in st.values()), len(st)

    def resume_image(self, user: str | None = None) -> str | None:
        """The image to open first: the one this user had open last, else the most recently saved
        one still in progress, else the first image not done, else the first readable one."""
        names = self.images()
        if not names:
            return None
        st = self.statuses()
        last = self.last_opened(user)
        if last and st.get(last) != "unreadable":
            return last
        busy = [n for n in names if st[n] == "in progress"]
        if busy:
            return max(busy, key=lambda n: self.annotation_path(n).stat().st_mtime)
        for n in names:
            if st[n] not in DONE_STATUSES + ("unreadable",):
                return n
        return next((n for n in names if st[n] != "unreadable"), names[0])


def photo_info(source, name: str):
    """Header checks of a project photo (a path or the file's bytes): racklay.data.image_info (a
    readable image within the pixel limit), then PNG/JPEG only and MAX_SIDE a side."""
    from racklay.data import DataError, image_info

    try:
        info = image_info(source, name)
    except DataError as e:
        raise StoreError(str(e)) from None
    if info.format not in ("PNG", "JPEG"):
        raise StoreError(f"{name}: {info.format} images are not accepted (PNG or JPEG only)")
    if max(info.width, info.height) > MAX_SIDE:
        raise StoreError(f"{name}: {info.width}x{info.height} pixels is over the limit of {MAX_SIDE} px a side")
    return info


def check_image_bytes(data: bytes, source: str) -> str:
    """Refuse anything but a complete PNG/JPEG within the size and pixel limits; decompression
    bombs are refused from the header, before any pixel is decoded. Returns 'PNG' or 'JPEG'."""
    from racklay.data import DataError, decode_image

    if len(data) > MAX_UPLOAD_BYTES:
        raise StoreError(f"{source}: {len(data) / 2**20:.1f} MB is over the {MAX_UPLOAD_BYTES // 2**20} MB limit")
    if not data:
        raise StoreError(f"{source}: empty file")
    info = photo_info(data, source)
    try:
        decode_image(data, source, info)
    except DataError as e:
        raise StoreError(str(e)) from None
    return info.format
