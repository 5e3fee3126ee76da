"""WareSynth recipes: every knob of the generator in one validated dataclass.

A recipe is a flat YAML mapping. The built-in ones (simple, complex, proxy_real, release, ...)
ship inside the package, ``racklay/synth/recipes/NAME.yaml``, read through importlib.resources so
a normal (non-editable) install finds them. ``base: NAME`` (a built-in name or a file) makes a
recipe start from another one's keys and list only what it changes. Keys not listed in `Recipe`
and values outside a field's range are rejected with one clear error *before* anything is
written. Command-line overrides use the same names: ``--set box_density=[0.2,0.9]``.

Ranges are written ``[lo, hi]`` and sampled uniformly per scene (integers for integer knobs).
"""
from __future__ import annotations

import dataclasses
import difflib
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import yaml

from ..yamlfile import read_yaml_mapping

#: the built-in recipes (package data; an installed package is a folder on disk, never a zip)
RECIPE_DIR = Path(str(resources.files("racklay.synth") / "recipes"))


class RecipeError(ValueError):
    """A recipe that cannot be used; the message names the recipe and the key."""


def _f(default, kind, lo=None, hi=None, doc=""):
    """A recipe field. kind: int, float, bool, str, path, irange/frange ([lo, hi]), splits,
    choice:a|b, weights:a|b; lo/hi bound every number."""
    return field(default_factory=(lambda d=default: list(d) if isinstance(d, list) else (dict(d) if isinstance(d, dict) else d)),
                 metadata={"kind": kind, "lo": lo, "hi": hi, "doc": doc})


@dataclass
class Recipe:
    # --- identity and output -------------------------------------------------------------
    name: str = _f("custom", "str", doc="recipe name, written into every meta file")
    domain: str = _f("synthetic", "choice:synthetic|proxy-real", doc="'proxy-real' marks the stand-in target domain")
    image_width: int = _f(470, "int", 32, 4096, "image width in pixels")
    image_height: int = _f(280, "int", 32, 4096, "image height in pixels")
    R: int = _f(4, "int", 1, 16, "layout channels = most shelves labelled (the lowest R visible ones; at most R visible unless tall_view_fraction)")
    layout_size: int = _f(512, "int", 16, 2048, "layout grid D (pixels a side)")
    extent_m: float = _f(8.0, "float", 1.0, 64.0, "metres covered by the layout grid")
    splits: dict = _f({"train": 0.6667, "val": 0.1667, "test": 0.1666}, "splits", doc="split fractions (paper: 8k/2k/2k)")
    # --- the considered rack ------------------------------------------------------------
    n_shelves: list = _f([3, 6], "irange", 1, 12, "shelves (boards that carry boxes) in the rack")
    shelf_height: list = _f([0.45, 0.8], "frange", 0.2, 2.5, "inter-shelf height in metres (board top to board top)")
    shelf_height_jitter: float = _f(0.0, "float", 0.0, 0.4, "relative per-level variation of the inter-shelf height")
    rack_length: list = _f([1.6, 3.0], "frange", 0.5, 6.0, "rack (shelf board) length along x, metres")
    rack_depth: list = _f([0.6, 1.1], "frange", 0.2, 2.0, "shelf board depth, metres")
    bottom_height: list = _f([0.08, 0.25], "frange", 0.0, 1.0, "height of the lowest board's top above the floor")
    board_thickness: float = _f(0.035, "float", 0.005, 0.2, "board thickness, metres")
    beam_height: list = _f([0.06, 0.12], "frange", 0.0, 0.3, "front/back beam height under each board")
    upright_width: float = _f(0.08, "float", 0.02, 0.3, "upright post width, metres")
    # --- pallet racking (drawn only where rack_style gives it a weight: other recipes keep their scenes) ---
    rack_style: dict = _f({"shelving": 1.0}, "weights:shelving|pallet|cube|wire|boltless|slotted", doc="probability of each rack style: shelving (boards on beams, boxes straight on them), pallet racking (beam pairs, loads on pallets), cube units (a grid of square cells between panels, a bin or small items in each), wire shelving (wire decks on four round posts), boltless shelving (perforated angle posts, a beam on every side of each level framing a chipboard or steel-panel deck) or slotted-angle shelving (slotted angle posts, steel panels with folded-down edges or chipboard on angle frames, no beam above the deck); boltless and slotted are sized by the shelving keys")
    pallet_levels: list = _f([2, 5], "irange", 1, 8, "pallet racking: storage levels, the floor position included")
    pallet_level_height: list = _f([1.2, 2.2], "frange", 0.5, 4.0, "pallet racking: beam level to beam level, metres")
    pallet_bay_length: list = _f([2.7, 3.6], "frange", 1.0, 6.0, "pallet racking: beam length (clear bay width), metres")
    pallet_rack_depth: list = _f([0.8, 1.2], "frange", 0.5, 2.0, "pallet racking: frame depth, metres")
    pallet_bay_fit: float = _f(0.0, "float", 0.0, 1.0, "pallet racking: probability that a rack's bays are sized for their pallets, as real bays are specified (2.7 m beams for three euro pallets turned): one footprint and orientation for every level, n pallets with pallet_gap between them and at both ends, n chosen so that the beams stay within pallet_bay_length where they can; otherwise the beam length is drawn from pallet_bay_length and each level draws its own footprint")
    floor_level: float = _f(0.5, "float", 0.0, 1.0, "pallet racking: probability that the floor under the first beam is a storage level (shelf channel 0, its board is the floor)")
    wire_deck: float = _f(0.3, "float", 0.0, 1.0, "pallet racking: probability of wire-mesh decks on the beams (else open beams)")
    beam_labels: float = _f(0.0, "float", 0.0, 1.0, "probability that a scene's racks carry location labels on their front beams (pallet racking, shelving, boltless and slotted beams or lips: a white, yellow or blue-banded label with a location code and a barcode, about one per metre of beam)")
    pallet_load: dict = _f({"cartons": 0.5, "wrapped": 0.35, "crates": 0.15}, "weights:cartons|wrapped|crates", doc="pallet racking: what stands on a pallet")
    pallet_gap: list = _f([0.06, 0.15], "frange", 0.0, 1.0, "pallet racking: clearance between neighbouring pallets, metres (one draw per level)")
    pallet_overhang: list = _f([0.0, 0.0], "frange", 0.0, 0.4, "pallet racking: a load may be wider than its pallet by up to this much on each side along the beams, metres (one draw per load; never past a neighbour or the beams' ends)")
    pallet_wide_fraction: float = _f(0.0, "float", 0.0, 1.0, "pallet racking: probability that two loads in neighbouring slots are one load on both pallets, the pallets moved together (long crates, appliance cartons, flat-packed boards: 1.6-2.5 m along the beams)")
    pallet_packing: float = _f(0.0, "float", 0.0, 1.0, "pallet racking: probability that a level's pallets stand packed at pallet_gap from each other (as in a bay sized for them) rather than spread evenly along the beams")
    pallet_load_height: list = _f([0.35, 1.0], "frange", 0.0, 1.0, "pallet racking: a load's height above its pallet as a fraction of the level's clear height above the pallet ~ U(lo, hi) (one draw per load; near 1: loads built up to the next beam's forklift clearance, as in a full warehouse)")
    # --- cube units (drawn only where rack_style gives them a weight) ---
    cube_columns: list = _f([2, 5], "irange", 1, 8, "cube units: cells side by side")
    cube_rows: list = _f([2, 5], "irange", 1, 8, "cube units: rows of cells (each row's floor panel is a shelf)")
    cube_cell: list = _f([0.28, 0.42], "frange", 0.1, 1.0, "cube units: inner width = height of a cell, metres")
    cube_depth: list = _f([0.3, 0.42], "frange", 0.1, 1.0, "cube units: depth, metres")
    cube_bin: float = _f(0.6, "float", 0.0, 1.0, "cube units: probability that a filled cell holds one bin filling most of it (else 1-4 small items)")
    # --- wire shelving (drawn only where rack_style gives it a weight) ---
    wire_length: list = _f([0.6, 1.85], "frange", 0.3, 3.0, "wire shelving: deck length between the posts, metres (36-72 in. units and shorter)")
    wire_depth: list = _f([0.3, 0.61], "frange", 0.2, 1.0, "wire shelving: deck depth, metres (14-24 in.)")
    wire_levels: list = _f([3, 6], "irange", 1, 8, "wire shelving: decks per unit")
    wire_level_height: list = _f([0.25, 0.5], "frange", 0.15, 1.0, "wire shelving: deck to deck, metres")
    # --- warehouse ------------------------------------------------------------------------
    background: dict = _f({"wall": 0.4, "busy": 0.6}, "weights:wall|busy", doc="probability of each background")
    wall_gap: list = _f([0.05, 0.6], "frange", 0.0, 5.0, "gap between the rack's back and the wall (wall background)")
    corridor_width: list = _f([2.5, 4.0], "frange", 1.0, 10.0, "corridor width in the occupancy map, metres")
    rack_density: float = _f(0.8, "float", 0.0, 1.0, "probability that a cell of the occupancy map holds a rack bay")
    rack_rows: int = _f(3, "int", 0, 8, "rack rows behind the considered one (busy background)")
    bays_per_side: int = _f(3, "int", 0, 10, "neighbouring bays on each side in the same row (busy background)")
    clutter: list = _f([2, 10], "irange", 0, 60, "clutter items (pallets, forklift-like blocks, extinguishers)")
    neighbour_fill: float = _f(0.0, "float", 0.0, 1.0, "the levels of every bay but the considered one are loaded at a density of at least this: box_density's draw d becomes f + (1 - f) d (0: as box_density; a busy warehouse's other bays are mostly full, and they are what a gap between two loads shows)")
    # --- boxes ----------------------------------------------------------------------------
    box_density: list = _f([0.0, 1.0], "frange", 0.0, 1.0, "per-shelf occupancy density ~ U(lo, hi)")
    flush_fraction: float = _f(0.0, "float", 0.0, 1.0, "shelving: probability that an item stands flush against its neighbour along the shelf (no gap: walls of cartons, one run in the layouts) instead of min_gap or more from it")
    min_gap: float = _f(0.03, "float", 0.0, 0.5, "minimum gap between boxes, metres")
    yaw_max_deg: float = _f(10.0, "float", 0.0, 45.0, "box yaw about the vertical ~ U(-r, r) degrees")
    max_stack: list = _f([1, 3], "irange", 1, 8, "boxes stack up to a random height in this range")
    crate_fraction: float = _f(0.25, "float", 0.0, 1.0, "probability that an item is a crate, not a carton")
    size_jitter: float = _f(0.12, "float", 0.0, 0.5, "relative size variation within a category")
    back_row: float = _f(0.5, "float", 0.0, 1.0, "probability of a second box row behind a shallow box")
    turn_fraction: float = _f(0.25, "float", 0.0, 1.0, "probability that an item stands turned, its two footprint sides swapped (a category's depth is then its width)")
    box_anchor: str = _f("front", "choice:front|centre", doc="where an item (the front row) stands across the shelf: 'front' at the shelf's front edge, set back by up to `setback`; 'centre' centred on the shelf's depth, as the paper authors' WareSynth places every item (its back rows then fit only behind a shallow item on a deep shelf)")
    setback: float = _f(0.6, "float", 0.0, 1.0, "box_anchor 'front': an item's set-back from the front edge is U(0, free depth) x U(0, setback) (0: every item flush with the front edge)")
    # --- camera ---------------------------------------------------------------------------
    focal_px: list = _f([330.0, 520.0], "frange", 50.0, 5000.0, "focal length in pixels (fx = fy)")
    long_lens_fraction: float = _f(0.0, "float", 0.0, 1.0, "probability that a camera zooms in: its focal length comes from long_focal_px instead of focal_px (phone zoom, crops of larger frames)")
    long_focal_px: list = _f([560.0, 2000.0], "frange", 50.0, 5000.0, "focal length in pixels of a zoomed camera (long_lens_fraction)")
    camera_distance: list = _f([0.9, 4.0], "frange", 0.2, 30.0, "horizontal distance from the rack front, metres")
    camera_height: list = _f([0.2, 4.5], "frange", 0.0, 30.0, "camera height above the floor, metres")
    camera_x: float = _f(0.2, "float", 0.0, 1.0, "camera x offset ~ U(-a, a) x rack length")
    framing: list = _f([1.0, 1.3], "frange", 0.3, 3.0, "camera distance / the distance at which the chosen shelves just fill the image height (< 1: close-ups where the rack overflows the frame)")
    yaw_jitter_deg: float = _f(3.0, "float", 0.0, 30.0, "camera yaw jitter ~ U(-a, a)")
    pitch_jitter_deg: float = _f(3.0, "float", 0.0, 30.0, "camera pitch jitter ~ U(-a, a)")
    roll_jitter_deg: float = _f(1.0, "float", 0.0, 15.0, "camera roll jitter ~ U(-a, a)")
    tall_view_fraction: float = _f(0.0, "float", 0.0, 1.0, "probability that a camera frames more levels than R (a tall rack photographed whole): the lowest R visible levels get the layout channels, as the labelling guide labels such a photo (docs/annotate.md); the others stay in the image, unlabelled (0: at most R levels visible)")
    tall_view_shelves: list = _f([0, 0], "irange", 0, 16, "shelving: shelves (more than R) of the racks photographed in a tall view (tall_view_fraction of the shelving racks get this many shelves and a camera that frames more than R of them; the others keep n_shelves and at most R visible); [0, 0]: a tall view is drawn per camera, on any rack with more than R levels")
    visible_fraction: float = _f(0.5, "float", 0.05, 1.0, "a shelf is visible when this fraction of its front opening's height is in the image")
    visible_fraction_board: float = _f(1.0, "float", 0.05, 1.0, "a shelf whose board's front edge is in the image is visible when this fraction of its front opening's height is (a level whose top the frame cuts, as labellers count one; 1.0: visible_fraction decides alone)")
    layout_extent: str = _f("bay", "choice:bay|frame|row", doc="what the layouts draw of a bay the image cuts: 'bay' the whole bay (the paper's data, `complex`), 'frame' the bay as far as the image shows it, as the labelling guide draws photos (docs/annotate.md): cut where the image's left and right edges meet its front at the height of the middle of its visible levels, and a level whose opening the image's top edge cuts ended there; 'row' as 'frame', but the shelves continue across shared uprights into the neighbouring bays of the row as far as the image shows them (the guide's 'bay or bays'; at most extent_m long)")
    detection_range_m: float = _f(12.0, "float", 0.5, 100.0, "range of detection d: farther shelves are not visible")
    # --- lighting -------------------------------------------------------------------------
    ambient: list = _f([0.2, 0.35], "frange", 0.0, 2.0, "ambient light level")
    light_intensity: list = _f([0.45, 0.85], "frange", 0.0, 5.0, "ceiling light intensity")
    light_spacing: list = _f([3.0, 5.0], "frange", 1.0, 20.0, "ceiling lights along corridors every ... metres")
    light_warmth: list = _f([-0.1, 0.1], "frange", -1.0, 1.0, "colour temperature shift (+ warm, - cool)")
    ceiling_height: list = _f([7.0, 10.0], "frange", 3.0, 30.0, "warehouse ceiling height, metres")
    shadows: bool = _f(True, "bool", doc="shadow map for the main light")
    ambient_occlusion: list = _f([0.0, 0.0], "frange", 0.0, 8.0, "strength of screen-space ambient occlusion (0 off; each pixel times ao ** strength, ao in [0, 1] from the depth buffer): how much light recesses lose (the slots between loads, under boards, inside a rack) that the ambient and fill lights otherwise reach as well as open faces")
    # --- look -----------------------------------------------------------------------------
    texture_family: str = _f("warehouse", "choice:warehouse|proxy", doc="procedural texture family")
    texture_dir: str = _f("", "path", doc="folder of your own images used as extra carton textures")
    tint_jitter: float = _f(0.08, "float", 0.0, 0.5, "per-object colour jitter")
    palette_random: float = _f(0.0, "float", 0.0, 1.0, "probability that the uprights, beams, boards and wall of a scene get random colours instead of the warehouse palette")
    antialias: int = _f(1, "int", 0, 16, "0 off, 1 edge AA from the exact instance map (cheap), >= 2 MSAA samples (slow on CPU)")
    # --- camera effects (proxy-real domain; off in the synthetic recipes) -------------------
    exposure: list = _f([1.0, 1.0], "frange", 0.1, 4.0, "exposure gain")
    white_balance: float = _f(0.0, "float", 0.0, 0.5, "per-channel gain shift ~ U(-a, a)")
    blur_sigma: list = _f([0.0, 0.0], "frange", 0.0, 5.0, "Gaussian blur sigma, pixels")
    noise_std: list = _f([0.0, 0.0], "frange", 0.0, 50.0, "sensor noise std (0..255 scale)")
    vignetting: list = _f([0.0, 0.0], "frange", 0.0, 1.0, "corner darkening")
    jpeg_quality: list = _f([0, 0], "irange", 0, 100, "JPEG round-trip quality (0 = off)")
    distortion_k1: list = _f([0.0, 0.0], "frange", -0.5, 0.5, "radial lens distortion k1 (image only; layouts stay metric)")
    # --- extra outputs --------------------------------------------------------------------
    write_depth: bool = _f(True, "bool", doc="depth/NNNNNN.png (uint16 millimetres)")
    write_normals: bool = _f(True, "bool", doc="normals/NNNNNN.png (camera-frame, 8-bit)")
    write_semantic: bool = _f(True, "bool", doc="semantic/NNNNNN.png")
    write_instance: bool = _f(True, "bool", doc="instance/NNNNNN.png (uint16)")
    write_kitti: bool = _f(True, "bool", doc="kitti/NNNNNN.txt labels")
    write_coco: bool = _f(True, "bool", doc="annotations/instances_*.json at the end")

    # ------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def fields_help(cls) -> str:
        return "\n".join(f"  {f.name:20s} {f.metadata['doc']}" for f in dataclasses.fields(cls))


_FIELDS = {f.name: f for f in dataclasses.fields(Recipe)}


def _check_value(key: str, value, src: str):
    f = _FIELDS[key]
    kind, lo, hi = f.metadata["kind"], f.metadata["lo"], f.metadata["hi"]
    where = f"{src}: key '{key}'"

    def num(v, integer):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise RecipeError(f"{where}: expected a number, got {v!r}")
        if integer and float(v) != int(v):
            raise RecipeError(f"{where}: expected an integer, got {v!r}")
        v = int(v) if integer else float(v)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise RecipeError(f"{where}: {v} out of range [{lo}, {hi}]")
        return v

    if kind in ("int", "float"):
        return num(value, kind == "int")
    if kind in ("irange", "frange"):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value, value]
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise RecipeError(f"{where}: expected a range [lo, hi], got {value!r}")
        a, b = (num(v, kind == "irange") for v in value)
        if a > b:
            raise RecipeError(f"{where}: range [{a}, {b}] has lo > hi")
        return [a, b]
    if kind == "bool":
        if not isinstance(value, bool):
            raise RecipeError(f"{where}: expected true or false, got {value!r}")
        return value
    if kind == "str":
        return str(value)
    if kind == "path":
        return "" if value in (None, "") else str(value)
    if kind.startswith("choice:"):
        allowed = kind.split(":", 1)[1].split("|")
        if value not in allowed:
            raise RecipeError(f"{where}: {value!r} is not one of {allowed}")
        return value
    if kind.startswith("weights:"):
        allowed = kind.split(":", 1)[1].split("|")
        if not isinstance(value, dict) or not value:
            raise RecipeError(f"{where}: expected a mapping like {{{allowed[0]}: 0.5, ...}}")
        out = {}
        for k, v in value.items():
            if k not in allowed:
                raise RecipeError(f"{where}: unknown choice {k!r} (allowed: {allowed})")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
                raise RecipeError(f"{where}: weight of {k!r} must be a number >= 0")
            out[k] = float(v)
        if sum(out.values()) <= 0:
            raise RecipeError(f"{where}: weights sum to 0")
        return out
    if kind == "splits":
        if not isinstance(value, dict) or not value:
            raise RecipeError(f"{where}: expected a mapping like {{train: 0.8, val: 0.1, test: 0.1}}")
        out = {}
        for k, v in value.items():
            if not isinstance(k, str) or not k.replace("_", "").isalnum():
                raise RecipeError(f"{where}: bad split name {k!r}")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
                raise RecipeError(f"{where}: fraction of split {k!r} must be a number >= 0")
            out[k] = float(v)
        if sum(out.values()) > 1 + 1e-6:
            raise RecipeError(f"{where}: split fractions sum to {sum(out.values()):.4f} > 1")
        return out
    raise AssertionError(kind)


def _unknown_key(key, src: str) -> RecipeError:
    close = difflib.get_close_matches(str(key), list(_FIELDS), n=1)
    hint = f" (did you mean '{close[0]}'?)" if close else ""
    return RecipeError(f"{src}: unknown key '{key}'{hint}")


def recipe_from_dict(data: dict, src: str = "recipe") -> Recipe:
    """Validate a mapping and build a Recipe; unknown keys and bad values raise RecipeError."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise RecipeError(f"{src}: expected a mapping of key: value, got {type(data).__name__}")
    kw = {}
    for key, value in data.items():
        if key not in _FIELDS:
            raise _unknown_key(key, src)
        kw[key] = _check_value(key, value, src)
    r = Recipe(**kw)
    if r.layout_size % 2:
        raise RecipeError(f"{src}: key 'layout_size' must be even, got {r.layout_size}")
    if r.tall_view_shelves[1] > 0 and r.tall_view_shelves[0] <= r.R:
        raise RecipeError(f"{src}: key 'tall_view_shelves': {r.tall_view_shelves} must draw more than R = {r.R} "
                          "shelves (a tall view frames more levels than R), or be [0, 0] (off)")
    if r.texture_dir and not Path(os.path.expanduser(r.texture_dir)).is_dir():
        raise RecipeError(f"{src}: key 'texture_dir': folder {r.texture_dir} not found")
    if r.texture_dir:        # an empty folder is refused here, before any output folder exists
        try:
            texture_files(r.texture_dir)
        except ValueError as e:
            raise RecipeError(f"{src}: key 'texture_dir': {e}") from None
    return r


def texture_files(folder: str) -> list[Path]:
    """The images in a `texture_dir` (sorted by name), checked before anything is generated: a
    missing or empty folder is a one-line error naming it."""
    from ..data import PHOTO_EXTS

    d = Path(folder).expanduser()
    if not d.is_dir():
        raise ValueError(f"{folder}: texture_dir is not a folder")
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in PHOTO_EXTS and not p.name.startswith("."))
    if not files:
        raise ValueError(f"{folder}: texture_dir holds no images ({'/'.join(PHOTO_EXTS)})")
    return files


def parse_override(text: str) -> tuple[str, object]:
    """`key=value` with a YAML value (`box_density=[0.2, 0.9]`, `shadows=false`)."""
    if "=" not in text:
        raise RecipeError(f"--set {text!r}: expected key=value")
    key, _, raw = text.partition("=")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError as e:
        raise RecipeError(f"--set {text!r}: value is not valid YAML ({e.__class__.__name__})") from None
    return key.strip(), value


def resolve_recipe_path(name_or_path: str) -> Path:
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists() or os.sep in name_or_path:
        if not p.is_file():
            raise RecipeError(f"{p}: recipe file not found")
        return p
    q = RECIPE_DIR / f"{name_or_path}.yaml"
    if not q.is_file():
        known = builtin_recipes()
        raise RecipeError(f"recipe '{name_or_path}' not found in {RECIPE_DIR} (known: {', '.join(known) or 'none'})")
    return q


def builtin_recipes() -> list[str]:
    """Names of the recipes shipped in RECIPE_DIR."""
    return sorted(x.stem for x in RECIPE_DIR.glob("*.yaml"))


def _recipe_file(path: Path, seen: tuple) -> dict:
    """A recipe file's keys, validated against the file, its `base` recipe's keys (recursively)
    under them; its name is its own `name`, else the file's stem."""
    data = read_yaml_mapping(path, "key: value", error=RecipeError)
    if not data:   # an unsaved or truncated file would otherwise render the defaults unnoticed
        raise RecipeError(f"{path}: empty recipe (no 'key: value' line); leave out --recipe for the defaults")
    data = dict(data)
    name = data.setdefault("name", path.stem)
    base = data.pop("base", None)
    if base is not None:
        if not isinstance(base, str) or not base:
            raise RecipeError(f"{path}: key 'base': expected a recipe name or file, got {base!r}")
        try:
            base_path = resolve_recipe_path(base)
        except RecipeError as e:
            raise RecipeError(f"{path}: key 'base': {e}") from None
        if base_path.resolve() in seen + (path.resolve(),):
            raise RecipeError(f"{path}: key 'base': recipe {base!r} is based on itself")
        data = {**_recipe_file(base_path, seen + (path.resolve(),)), **data, "name": name}
    recipe_from_dict(data, str(path))   # errors in the file are reported against the file
    return data


def load_recipe(name_or_path: str | None = None, overrides: list[str] | dict | None = None) -> Recipe:
    """Load a recipe by name (a built-in one, RECIPE_DIR) or path, apply `key=value` overrides,
    validate everything, and return it."""
    data, src = {}, "recipe defaults"
    if name_or_path:
        path = resolve_recipe_path(name_or_path)
        src = str(path)
        data = _recipe_file(path, ())
    if overrides:
        items = overrides.items() if isinstance(overrides, dict) else (parse_override(o) for o in overrides)
        for k, v in items:
            if k not in _FIELDS:
                raise _unknown_key(k, "--set")
            data[k] = v
        src = f"{src} with --set overrides"
    return recipe_from_dict(data, src)
