"""The annotation file format (one JSON per image) and the project settings file, with strict
validation on load, the labelme way: a file that does not match the schema is refused with one
line naming the file and the field, and is never overwritten by the tool.

Everything the labeller clicks is stored in *image pixels* (corners, shelf-edge points, box
rectangles), so moving a rack corner later re-maps every shelf and box through the new
homography. Metric values (shelf heights, box ranges) are derived by `annotate.geometry`, never
stored as the source of truth. The format is documented in docs/annotation-format.md and
written down as types here (`Annotation`, `Settings` and their parts, TypedDicts); the
validators below are the one place that checks a file against them.
"""
from __future__ import annotations

import copy
import json
import math
import os
import unicodedata
from pathlib import Path
from typing import Any, TypedDict

SCHEMA_VERSION = 1
SETTINGS_VERSION = 1
STATUSES = ("todo", "in progress", "done", "needs review", "approved")
BOX_SOURCES = ("manual", "model")

#: rack presets shipped with a new project: width (along the rack) x height x depth in metres
DEFAULT_PRESETS = [
    {"name": "boltless 2.0 × 2.0 × 0.6 m", "width": 2.0, "height": 2.0, "depth": 0.6},
    {"name": "boltless 1.5 × 1.8 × 0.5 m", "width": 1.5, "height": 1.8, "depth": 0.5},
    {"name": "longspan 2.4 × 2.4 × 0.8 m", "width": 2.4, "height": 2.4, "depth": 0.8},
    {"name": "pallet rack bay 2.7 × 3.0 × 1.1 m", "width": 2.7, "height": 3.0, "depth": 1.1},
]


class SchemaError(ValueError):
    """An annotation or settings file that breaks the schema; the message names file and field."""


# --- the formats, as types: what validate_annotation / validate_settings accept ------------------
# (required fields in the first class, optional ones in the `total=False` class built on it; the
# validators take their field lists from these, so the two cannot drift apart)
Point = list  # [x, y] in photo pixels (x right, y down)


class _RackFields(TypedDict):
    corners: list[Point]        # 0-4 clicked corners of the rack's front face, any order
    width: float | None         # metres (null until a preset or a value is set)
    height: float | None
    depth: float | None


class Rack(_RackFields, total=False):
    preset: str | None
    size_confirmed: bool        # absent = confirmed (files from before it existed)


class Shelf(TypedDict):
    id: int
    point: Point                # one click on the board's front edge


class _BoxFields(TypedDict):
    id: int
    p0: Point                   # two opposite corners of the box's front face
    p1: Point


class Box(_BoxFields, total=False):
    depth: float | None         # metres; absent = project default_depth or the rack depth
    front_offset: float | None  # metres from the rack's front face (absent = 0)
    source: str                 # BOX_SOURCES
    score: float | None         # a model proposal's mean box probability
    on_board: bool              # false: rests on something (its bottom is where it was clicked)


class _ImportedFields(TypedDict):
    top: str | None             # paths inside the project of read-only imported layouts
    front: str | None


class Imported(_ImportedFields, total=False):
    dataset: str
    id: str


class _AnnotationFields(TypedDict):
    schema_version: int         # SCHEMA_VERSION
    image: str                  # the photo's plain file name
    image_size: list[int]       # [width, height] in pixels
    version: int                # save counter, for the conflict check
    status: str                 # STATUSES
    rack: Rack
    shelves: list[Shelf]
    boxes: list[Box]


class Annotation(_AnnotationFields, total=False):
    """One annotations/NAME.json (docs/annotation-format.md)."""

    proposals: list[Box]        # model proposals waiting to be accepted or rejected
    rejected: list[list[float]]  # [shelf, u0, u1, v0, v1] on the rack plane, metres
    imported: Imported | None
    updated_by: str | None
    updated_at: str


class Preset(TypedDict):
    name: str
    width: float
    height: float
    depth: float


class _SettingsFields(TypedDict):
    schema_version: int         # SETTINGS_VERSION
    R: int
    D: int
    extent: float
    presets: list[Preset]


class Settings(_SettingsFields, total=False):
    """project.json (docs/annotation-format.md)."""

    default_depth: float | None
    default_preset: str | None
    box_snap: float
    pixel_aspect: float     # width / height of one photo pixel (photos squeezed to a square: > 1); 1 if absent
    version: int


# --- small validators ------------------------------------------------------------------------
def _fail(source: str, field: str, msg: str):
    raise SchemaError(f"{source}: field '{field}': {msg}")


def _num(v, source, field, lo=None, hi=None, lo_open=False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        _fail(source, field, f"expected a finite number, got {v!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        _fail(source, field, f"must be {'>' if lo_open else '>='} {lo}, got {v}")
    if hi is not None and v > hi:
        _fail(source, field, f"must be <= {hi}, got {v}")
    return float(v)


def _int(v, source, field, lo=None, hi=None) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        _fail(source, field, f"expected an integer, got {v!r}")
    if lo is not None and v < lo:
        _fail(source, field, f"must be >= {lo}, got {v}")
    if hi is not None and v > hi:
        _fail(source, field, f"must be <= {hi}, got {v}")
    return v


def _str(v, source, field, choices=None, allow_empty=False) -> str:
    if not isinstance(v, str) or (not allow_empty and not v):
        _fail(source, field, f"expected a non-empty string, got {v!r}")
    if choices is not None and v not in choices:
        _fail(source, field, f"must be one of {', '.join(map(repr, choices))}; got {v!r}")
    return v


def _bool(v, source, field) -> bool:
    if not isinstance(v, bool):
        _fail(source, field, f"expected true or false, got {v!r}")
    return v


def _point(v, source, field) -> list[float]:
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        _fail(source, field, f"expected [x, y] pixel coordinates, got {v!r}")
    return [_num(v[0], source, f"{field}[0]"), _num(v[1], source, f"{field}[1]")]


def _obj(v, source, field, kind: type) -> dict:
    """v is an object with the fields of the TypedDict `kind`: every required one, no other."""
    if not isinstance(v, dict):
        _fail(source, field, f"expected an object, got {type(v).__name__}")
    extra = sorted(set(v) - kind.__required_keys__ - kind.__optional_keys__)
    if extra:
        _fail(source, f"{field}.{extra[0]}" if field else extra[0], "unknown field")
    for k in sorted(kind.__required_keys__):
        if k not in v:
            _fail(source, f"{field}.{k}" if field else k, "missing")
    return v


#: the longest photo name the tool stores (its annotation, lock and history files add ~10 characters
#: to it; file systems allow 255 bytes, a UTF-8 character takes up to 4)
MAX_NAME_CHARS = 150


def check_image_name(name: str, source: str = "image name", field: str = "image") -> str:
    """A plain file name: the only kind the tool stores. Any language and the characters cameras
    and file managers write ('IMG_0001 (1).jpg', 'Regal Übersicht.jpg'); not a folder or a path
    ('/', '\\'), not hidden (a leading '.'), no surrounding spaces, no control or invisible
    formatting characters (nor the undecodable bytes of a name in another encoding)."""
    if not isinstance(name, str) or not name:
        _fail(source, field, f"not a plain file name: {name!r}")
    bad = None
    if "/" in name or "\\" in name:
        bad = "it names a folder"
    elif name.startswith("."):
        bad = "a hidden file"
    elif name != name.strip():
        bad = "spaces around it"
    elif len(name) > MAX_NAME_CHARS:
        bad = f"longer than {MAX_NAME_CHARS} characters"
    elif any(unicodedata.category(c).startswith("C") for c in name):
        bad = "a control, invisible or undecodable character"
    if bad:
        _fail(source, field, f"not a plain file name: {name!r} ({bad}; rename the photo)")
    return name


# --- annotation -------------------------------------------------------------------------------
def new_annotation(image: str, width: int, height: int) -> Annotation:
    """A fresh annotation for an image of width x height pixels."""
    return {
        "schema_version": SCHEMA_VERSION,
        "image": image,
        "image_size": [int(width), int(height)],
        "version": 0,
        "status": "todo",
        "rack": {"corners": [], "width": None, "height": None, "depth": None, "preset": None},
        "shelves": [],
        "boxes": [],
        "proposals": [],
        "rejected": [],
        "imported": None,
        "updated_by": None,
    }


def _validate_box(b, source, field) -> Box:
    _obj(b, source, field, Box)
    _int(b["id"], source, f"{field}.id", lo=0)
    _point(b["p0"], source, f"{field}.p0")
    _point(b["p1"], source, f"{field}.p1")
    if b.get("depth") is not None:
        _num(b["depth"], source, f"{field}.depth", lo=0, hi=100, lo_open=True)
    if b.get("front_offset") is not None:
        _num(b["front_offset"], source, f"{field}.front_offset", lo=0, hi=100)
    if "source" in b:
        _str(b["source"], source, f"{field}.source", BOX_SOURCES)
    if b.get("score") is not None:
        _num(b["score"], source, f"{field}.score", lo=0, hi=1)
    if "on_board" in b:
        _bool(b["on_board"], source, f"{field}.on_board")
    return b


def validate_annotation(d: Any, source: str = "annotation") -> Annotation:
    """Check an annotation dict against the schema; return it unchanged or raise SchemaError."""
    _obj(d, source, "", Annotation)
    sv = d["schema_version"]
    if sv != SCHEMA_VERSION:
        _fail(source, "schema_version", f"this tool reads version {SCHEMA_VERSION}, the file has {sv!r}")
    check_image_name(d["image"], source)
    sz = d["image_size"]
    if not isinstance(sz, list) or len(sz) != 2:
        _fail(source, "image_size", f"expected [width, height], got {sz!r}")
    _int(sz[0], source, "image_size[0]", lo=1)
    _int(sz[1], source, "image_size[1]", lo=1)
    _int(d["version"], source, "version", lo=0)
    _str(d["status"], source, "status", STATUSES)
    rack = _obj(d["rack"], source, "rack", Rack)
    if not isinstance(rack["corners"], list) or len(rack["corners"]) > 4:
        _fail(source, "rack.corners", "expected a list of at most 4 [x, y] points")
    for i, p in enumerate(rack["corners"]):
        _point(p, source, f"rack.corners[{i}]")
    for k in ("width", "height", "depth"):
        if rack[k] is not None:
            _num(rack[k], source, f"rack.{k}", lo=0, hi=100, lo_open=True)
    if rack.get("preset") is not None:
        _str(rack["preset"], source, "rack.preset")
    if "size_confirmed" in rack:
        _bool(rack["size_confirmed"], source, "rack.size_confirmed")
    if not isinstance(d["shelves"], list):
        _fail(source, "shelves", "expected a list")
    for i, s in enumerate(d["shelves"]):
        _obj(s, source, f"shelves[{i}]", Shelf)
        _int(s["id"], source, f"shelves[{i}].id", lo=0)
        _point(s["point"], source, f"shelves[{i}].point")
    for key in ("boxes", "proposals"):
        items = d.get(key, [])
        if not isinstance(items, list):
            _fail(source, key, "expected a list")
        for i, b in enumerate(items):
            _validate_box(b, source, f"{key}[{i}]")
    ids = [b["id"] for b in d["boxes"]]
    if len(set(ids)) != len(ids):
        _fail(source, "boxes", "box ids must be unique")
    rej = d.get("rejected", [])
    if not isinstance(rej, list):
        _fail(source, "rejected", "expected a list")
    for i, r in enumerate(rej):
        if not isinstance(r, list) or len(r) != 5:
            _fail(source, f"rejected[{i}]", "expected [shelf, x0, x1, z0, z1]")
        for j, v in enumerate(r):
            _num(v, source, f"rejected[{i}][{j}]")
    imp = d.get("imported")
    if imp is not None:
        _obj(imp, source, "imported", Imported)
        for k in ("top", "front"):
            if imp[k] is not None:
                p = _str(imp[k], source, f"imported.{k}")
                if p.startswith(("/", "\\")) or ".." in Path(p).parts:
                    _fail(source, f"imported.{k}", f"must be a path inside the project, got {p!r}")
    if d.get("updated_by") is not None:
        _str(d["updated_by"], source, "updated_by", allow_empty=True)
    return d


#: how far outside its photo a clicked point may lie, as a fraction of the photo's longer side:
#: clicks land on the photo, so a point further out comes from an edited or broken file
PHOTO_MARGIN = 0.05
#: the smallest box side, in photo pixels (a narrower box has no area to draw)
MIN_BOX_PX = 1.0


#: a rack's width, height and depth in metres, from a small cube unit to a high-bay rack (a size
#: outside, e.g. 1e-9 typed for 1, draws layouts of nothing)
RACK_SIZE_M = (0.05, 100.0)


def photo_problems(ann: Annotation, width: int, height: int, name: str | None = None) -> list[str]:
    """Every way a (schema-valid) annotation does not fit its photo of width x height pixels
    (named `name`): a different image name or image_size, a rack size outside RACK_SIZE_M, rack
    corners, shelf points or box corners outside the photo (beyond PHOTO_MARGIN), coinciding rack
    corners, boxes without area.
    One line each, naming the item by its id (stable when other items are added or deleted);
    empty when the annotation fits. The one check behind `annotate export` and the server's
    refusal to save an edit that breaks it (annotate.store.Project.save)."""
    out: list[str] = []
    if name is not None and ann["image"] != name:
        out.append(f"field 'image' says {ann['image']!r}, but the photo is {name!r}")
    sw, sh = ann["image_size"]
    if (sw, sh) != (width, height):
        out.append(f"field 'image_size' says {sw}x{sh}, but the photo is {width}x{height} pixels")
    m = PHOTO_MARGIN * max(width, height)

    def outside(what: str, p) -> None:
        x, y = p
        if not (-m <= x <= width + m and -m <= y <= height + m):
            out.append(f"{what} at ({x:.6g}, {y:.6g}) is outside the {width}x{height} photo")

    for k in ("width", "height", "depth"):
        v = ann["rack"].get(k)
        if v is not None and not RACK_SIZE_M[0] <= v <= RACK_SIZE_M[1]:
            out.append(f"rack {k} {v:.6g} m is not a rack's size ({RACK_SIZE_M[0]:g} to {RACK_SIZE_M[1]:g} m)")
    corners = ann["rack"]["corners"]
    for i, p in enumerate(corners):
        outside(f"rack corner {i + 1}", p)
    for i in range(len(corners)):
        for j in range(i + 1, len(corners)):
            if math.dist(corners[i], corners[j]) < 1.0:
                out.append(f"rack corners {i + 1} and {j + 1} coincide")
    for s in ann["shelves"]:
        outside(f"shelf {s['id']}", s["point"])
    for b in ann["boxes"]:
        outside(f"box {b['id']} corner p0", b["p0"])
        outside(f"box {b['id']} corner p1", b["p1"])
        dx, dy = abs(b["p1"][0] - b["p0"][0]), abs(b["p1"][1] - b["p0"][1])
        if dx < MIN_BOX_PX or dy < MIN_BOX_PX:
            out.append(f"box {b['id']} has no area ({dx:.3g} x {dy:.3g} px)")
    return out


def _read_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise SchemaError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}, column {e.colno})") from None
    except UnicodeDecodeError:
        raise SchemaError(f"{path}: not UTF-8 text") from None


def load_annotation(path: str | os.PathLike) -> Annotation:
    """Read and validate an annotation file. Raises SchemaError naming the file."""
    return validate_annotation(_read_json(Path(path)), str(path))


# --- project settings -------------------------------------------------------------------------
#: the pixel aspects a project may declare (a 21:9 frame squeezed to a square is 2.33)
PIXEL_ASPECT_RANGE = (0.25, 4.0)


def pixel_aspect(settings: Settings) -> float:
    """Width / height of one photo pixel in this project (1 unless `pixel_aspect` says otherwise)."""
    return float(settings.get("pixel_aspect") or 1.0)


def default_settings() -> Settings:
    return {
        "schema_version": SETTINGS_VERSION,
        "R": 4,
        "D": 512,
        "extent": 8.0,
        "default_depth": None,  # None: a box is as deep as its shelf
        "box_snap": 0.05,  # a box bottom within this many metres of a board stands on it
        "presets": copy.deepcopy(DEFAULT_PRESETS),
        "default_preset": DEFAULT_PRESETS[0]["name"],
    }


def validate_settings(d: Any, source: str = "project settings") -> Settings:
    _obj(d, source, "", Settings)
    if "version" in d:
        _int(d["version"], source, "version", lo=0)
    if d["schema_version"] != SETTINGS_VERSION:
        _fail(source, "schema_version", f"this tool reads version {SETTINGS_VERSION}, the file has {d['schema_version']!r}")
    _int(d["R"], source, "R", lo=1, hi=32)
    D = _int(d["D"], source, "D", lo=16, hi=4096)
    if D % 2:
        _fail(source, "D", f"must be even, got {D}")
    _num(d["extent"], source, "extent", lo=0, hi=1000, lo_open=True)
    if d.get("default_depth") is not None:
        _num(d["default_depth"], source, "default_depth", lo=0, hi=100, lo_open=True)
    if d.get("box_snap") is not None:
        _num(d["box_snap"], source, "box_snap", lo=0, hi=1)
    if d.get("pixel_aspect") is not None:
        _num(d["pixel_aspect"], source, "pixel_aspect", lo=PIXEL_ASPECT_RANGE[0], hi=PIXEL_ASPECT_RANGE[1])
    if not isinstance(d["presets"], list):
        _fail(source, "presets", "expected a list")
    names = []
    for i, p in enumerate(d["presets"]):
        _obj(p, source, f"presets[{i}]", Preset)
        names.append(_str(p["name"], source, f"presets[{i}].name"))
        for k in ("width", "height", "depth"):
            _num(p[k], source, f"presets[{i}].{k}", lo=0, hi=100, lo_open=True)
    if len(set(names)) != len(names):
        _fail(source, "presets", "preset names must be unique")
    if d.get("default_preset") is not None and d["default_preset"] not in names:
        _fail(source, "default_preset", f"{d['default_preset']!r} is not one of the presets")
    return d


def load_settings(path: str | os.PathLike) -> Settings:
    """Read and validate a project settings file. Raises SchemaError naming the file."""
    return validate_settings(_read_json(Path(path)), str(path))


def preset(settings: Settings, name: str | None) -> Preset | None:
    for p in settings["presets"]:
        if p["name"] == name:
            return p
    return None
