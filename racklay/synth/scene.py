"""Scene sampling: pure data, no rendering. A `Scene` is a list of cuboids/cylinders with
materials and semantic classes, the considered rack with its shelves and boxes, a camera and
lights. The ground truth (layouts, 3D boxes) is computed from this description, never from
rendered pixels.

World frame: x along the considered rack (to the camera's right), y away from the camera
(into the rack), z up, floor at z = 0. The considered rack is centred at x = y = 0, so every
shelf frame of the layout convention (racklay.layout) is the world frame shifted up to that
shelf's board top: shelf-frame (x, y, z) = world (x, y, z - board_top).

Camera frame: OpenCV (x right, y down, z forward). X_cam = R @ X_world + t, pixel = K @ X_cam.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .. import layout as L
from ..camera import PinholeCamera
from .effects import distort_points, k1_limit
from .recipe import Recipe

# --- semantic classes ---------------------------------------------------------------------
SEMANTIC_CLASSES = ("void", "floor", "wall", "rack", "shelf", "box", "crate", "clutter", "pallet")
SEM = {name: i for i, name in enumerate(SEMANTIC_CLASSES)}

# --- item categories: 6 cartons + 2 crates, nominal size (sx along the rack, sy deep, sz up) ---
CATEGORIES = (
    ("carton_small", (0.30, 0.25, 0.22)),
    ("carton_medium", (0.40, 0.30, 0.30)),
    ("carton_long", (0.60, 0.40, 0.28)),
    ("carton_flat", (0.50, 0.40, 0.14)),
    ("carton_tall", (0.30, 0.30, 0.46)),
    ("carton_large", (0.55, 0.45, 0.42)),
    ("crate_blue", (0.40, 0.30, 0.24)),
    ("crate_red", (0.60, 0.40, 0.32)),
    # load units of pallet racking: a pallet and what stands on it are one box (racklay.layout)
    ("pallet_cartons", (1.2, 0.8, 1.2)),
    ("pallet_wrapped", (1.2, 0.8, 1.2)),
    ("pallet_crates", (1.2, 0.8, 1.0)),
)
CATEGORY_NAMES = tuple(c[0] for c in CATEGORIES)
CARTONS = tuple(i for i, c in enumerate(CATEGORY_NAMES) if c.startswith("carton"))
CRATES = tuple(i for i, c in enumerate(CATEGORY_NAMES) if c.startswith("crate"))
PALLET_UNITS = {c[len("pallet_"):]: i for i, c in enumerate(CATEGORY_NAMES) if c.startswith("pallet_")}
PALLET_HEIGHT = 0.144     # a euro pallet's height, metres
PALLET_FOOTPRINTS = ((1.2, 0.8), (1.2, 1.0))   # euro and UK/industrial pallets, metres
DECK_LOOSE = 0.35         # a wire-deck level holds loose cartons / crates (no pallets) this often
WIRE_POST = 0.025         # wire shelving: post diameter, metres
WIRE_TRUSS = 0.03         # wire shelving: height of a deck's front / back frame under its top, metres
BOLTLESS_ANGLE = 0.04     # boltless shelving: flange width of the angle posts, metres
BOLTLESS_PLATE = 0.003    # boltless shelving: steel thickness of posts and beams, metres
BOLTLESS_LIP = 0.008      # boltless shelving: how far a level's beams rise above its deck top, metres
BOLTLESS_RIB = 0.02       # boltless shelving: depth of the stiffening ribs under a steel-panel deck, metres
BOLTLESS_BOARD = 0.016    # boltless shelving: thickness of a chipboard deck, metres
SLOTTED_PLATE = 0.0015    # slotted-angle shelving: steel-panel thickness, metres
#: slotted-angle shelving finishes (grey, light grey, green, blue, cream) and how often each is drawn
SLOTTED_FINISHES = (((0.5, 0.53, 0.56), 0.45), ((0.76, 0.77, 0.78), 0.2), ((0.3, 0.45, 0.36), 0.15),
                    ((0.2, 0.32, 0.6), 0.1), ((0.88, 0.86, 0.78), 0.1))
#: boltless shelving finishes (blue, grey, orange, white, black, green) and how often each is drawn
BOLTLESS_FINISHES = (((0.12, 0.22, 0.62), 0.35), ((0.6, 0.62, 0.64), 0.25), ((0.92, 0.45, 0.1), 0.15),
                     ((0.9, 0.9, 0.88), 0.1), ((0.12, 0.12, 0.13), 0.1), ((0.2, 0.45, 0.3), 0.05))
#: styles whose bays in a row share uprights and levels: layout_extent 'row' continues their shelves
ROW_STYLES = ("shelving", "pallet", "boltless", "slotted")
#: wire shelving finishes (chrome, black / white / green epoxy) and how often each is drawn
WIRE_FINISHES = (((0.9, 0.9, 0.92), 0.5), ((0.1, 0.1, 0.11), 0.25), ((0.9, 0.9, 0.87), 0.15), ((0.3, 0.45, 0.36), 0.1))


@dataclass
class Obj:
    """One renderable solid: a cuboid (or a vertical cylinder inscribed in it)."""

    center: tuple          # world (x, y, z) of the solid's centre
    size: tuple            # (sx, sy, sz) along its own axes
    yaw: float             # radians about z
    material: str          # texture bank key
    semantic: int
    tint: tuple = (1.0, 1.0, 1.0)
    shape: str = "box"     # "box" | "cylinder" | "none" (not drawn: a load unit whose parts are drawn)
    category: int = -1     # index into CATEGORIES for cartons/crates
    shelf: int = -1        # shelf index of the considered rack (-1 elsewhere)
    layout_box: L.Box | None = None  # the same item in its shelf frame (considered rack only)
    part_of: int = -1      # index of the load unit this drawn part belongs to (its pixels are the unit's)

    def corners(self) -> np.ndarray:
        """8 x 3 world corners of the cuboid (bottom 4 counter-clockwise, then top 4)."""
        return cuboid_corners([self])[0]


_UNIT_CORNERS = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                          [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], np.float64) / 2


def cuboid_corners(objs) -> np.ndarray:
    """(N, 8, 3) world corners of many cuboids at once (bottom 4 counter-clockwise, then top 4)."""
    if not objs:
        return np.zeros((0, 8, 3))
    size = np.array([o.size for o in objs], np.float64)
    centre = np.array([o.center for o in objs], np.float64)
    yaw = np.array([o.yaw for o in objs], np.float64)
    local = _UNIT_CORNERS[None] * size[:, None, :]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    out = np.empty_like(local)
    out[..., 0] = c * local[..., 0] - s * local[..., 1]
    out[..., 1] = s * local[..., 0] + c * local[..., 1]
    out[..., 2] = local[..., 2]
    return out + centre[:, None, :]


@dataclass
class ShelfInfo:
    board_top: float       # world z of the board's top surface
    clear_height: float    # inter-shelf height (board top to next board top; nominal for the top shelf)
    max_item_top: float    # highest allowed item top above the board (below the next beam)
    items: list = field(default_factory=list)  # indices into Scene.objects


@dataclass
class Camera(PinholeCamera):
    """The render camera (racklay.camera.PinholeCamera, world frame) with its image size and the
    radial distortion applied to the image after rendering."""
    width: int = 0
    height: int = 0
    k1: float = 0.0

    @classmethod
    def from_meta(cls, meta: dict) -> Camera:
        """The render camera of a WareSynth meta file (written by `groundtruth.scene_meta`)."""
        c = meta["camera"]
        K, R, t = (np.array(c[k], np.float64) for k in ("K", "R", "t"))
        w, h = meta["image_size"]
        return cls(K, R, t, width=int(w), height=int(h), k1=float(c.get("distortion_k1", 0.0)))

    def image_points(self, pts) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> (where the rendered, lens-distorted image shows them, N x 2,
        pixel (0, 0)'s corner at the origin; their camera-frame z, N)."""
        uv, z = self.project_z(pts)
        return distort_points(self.K, self.k1, uv), z

    def lens_holds(self, uv: np.ndarray) -> np.ndarray:
        """Where the distortion model holds for undistorted pixels `uv` (N, 2): barrel distortion
        folds points far outside the image back into it, so only the part of the lens where the
        distorted radius still grows with the true one, r (1 + k1 r²), counts."""
        r2 = ((uv[:, 0] - self.K[0, 2]) / self.K[0, 0]) ** 2 + ((uv[:, 1] - self.K[1, 2]) / self.K[1, 1]) ** 2
        return 1 + 3 * self.k1 * r2 > 0


@dataclass
class Light:
    position: tuple
    color: tuple
    intensity: float


@dataclass
class Scene:
    index: int
    seed: int
    recipe: str
    objects: list
    shelves: list              # ShelfInfo, bottom-up, of the considered rack
    rack_length: float
    rack_depth: float
    visible: list              # indices of visible shelves, lowest first (channel 0 = visible[0])
    camera: Camera
    lights: list
    ambient: float
    ambient_color: tuple
    main_light: int            # index of the shadow-casting light
    background: str
    occupancy: list            # rows of the bay occupancy map (strings, '#' rack, '.' free, '=' corridor)
    effects: dict
    domain: str = "synthetic"
    shadows: bool = True          # the key light casts shadows
    occlusion: float = 0.0        # ambient-occlusion strength (render.ambient_occlusion), 0 = none
    light_falloff: float = 6.0    # metres at which a light's intensity has halved
    rack_style: str = "shelving"  # "shelving" | "pallet" | "cube" | "wire" | "boltless" | "slotted" (Recipe.rack_style)
    layout_window: tuple | None = None  # (x0, x1): the part of the bay the layouts draw (Recipe.layout_extent)
    layout_heights: list | None = None  # per visible shelf: the height of its opening drawn, None: all (ditto)
    layout_row: tuple | None = None     # (x0, x1): the row of bays the shelves continue into (layout_extent 'row')
    row_boxes: list | None = None       # per shelf: the neighbouring bays' boxes, x in the considered bay's frame

    def layout_inputs(self) -> list[tuple[L.Shelf, list[L.Box]]]:
        """(Shelf, boxes in the shelf frame) of each visible shelf, lowest first, as far up as the
        layouts draw it (`layout_heights`: a level the frame's top cuts ends there, its boxes cut
        at that height); along x the whole bay (the layouts draw `layout_window` of it) or, with
        `layout_row`, a shelf centred on the considered bay reaching over the whole row of bays,
        with the neighbouring bays' boxes (the window then always lies within the row)."""
        out = []
        length = self.rack_length
        if self.layout_row is not None:
            length = 2 * max(-self.layout_row[0], self.layout_row[1])
        for k, si in enumerate(self.visible):
            sh = self.shelves[si]
            boxes = [self.objects[i].layout_box for i in sh.items]
            if self.row_boxes is not None:
                boxes += self.row_boxes[si]
            clear = sh.clear_height
            shown = self.layout_heights[k] if self.layout_heights else None
            if shown is not None:
                clear = shown
                boxes = [replace(b, sz=min(b.sz, shown - b.z0)) for b in boxes if b.z0 < shown]
            out.append((L.Shelf(length, self.rack_depth, clear), boxes))
        return out


def _u(rng, rng_pair):
    lo, hi = rng_pair
    return float(lo) if lo == hi else float(rng.uniform(lo, hi))


def _ui(rng, rng_pair):
    lo, hi = rng_pair
    return int(rng.integers(lo, hi + 1))


def _tint(rng, amount, base=(1.0, 1.0, 1.0)):
    """Colour jitter: a shared brightness change plus a per-channel one, each ~ U(-a, a).
    (Written out: a scene draws it for each of its ~1,000 solids.)"""
    rnd = rng.random
    j0, j1, j2, j3 = ((rnd() * 2 - 1) * amount, (rnd() * 2 - 1) * amount, (rnd() * 2 - 1) * amount,
                      (rnd() * 2 - 1) * amount)
    s = 1 + j3
    return (min(max(base[0] * (s + j0), 0.05), 2.0), min(max(base[1] * (s + j1), 0.05), 2.0),
            min(max(base[2] * (s + j2), 0.05), 2.0))


def _random_colour(rng, v_min: float = 0.12) -> tuple:
    """A paint colour of any hue: dark to light, grey to saturated (domain randomisation)."""
    import colorsys

    h, s, v = float(rng.uniform(0, 1)), float(rng.uniform(0, 1)) ** 1.5, float(rng.uniform(v_min, 1.0))
    return tuple(max(c, 0.05) for c in colorsys.hsv_to_rgb(h, s, v))


class SceneRNG:
    """Scalar random draws for scene sampling (Python's Mersenne Twister: ~20x cheaper per
    scalar than numpy's Generator, and its sequence for an integer seed is stable across
    platforms and Python versions). numpy-like method names."""

    def __init__(self, seed: int):
        import random

        self._r = random.Random(seed)
        self.random = self._r.random   # the hottest draw (tints) without a wrapper call: shadows the method below

    def random(self) -> float:
        """Uniform float in [0, 1)."""
        return self._r.random()

    def uniform(self, lo: float = 0.0, hi: float = 1.0) -> float:
        return lo + (hi - lo) * self._r.random()

    def integers(self, lo: int, hi: int | None = None) -> int:
        """Uniform integer in [lo, hi) (or [0, lo) when hi is None)."""
        if hi is None:
            lo, hi = 0, lo
        return lo + self._r.randrange(hi - lo)

    def choice(self, options, p=None):
        options = list(options)
        if p is None:
            return options[self.integers(len(options))]
        x, acc = self.random() * float(sum(p)), 0.0
        for o, w in zip(options, p):
            acc += w
            if x < acc:
                return o
        return options[-1]


def scene_rng(seed: int, index: int) -> SceneRNG:
    """The random stream of one image: depends only on (seed, index), not on sharding/workers."""
    ss = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(index), 0x5EED])
    return SceneRNG(int(ss.generate_state(2, np.uint64)[0]))


# --- items on one shelf ----------------------------------------------------------------------
def _item_size(rng, r: Recipe, cat: int) -> list[float]:
    base = CATEGORIES[cat][1]
    return [b * (1 + (rng.random() * 2 - 1) * r.size_jitter) for b in base]


def _pick(rng, options):
    return options[int(rng.integers(len(options)))]


def _category(rng, r: Recipe) -> int:
    return _pick(rng, CRATES) if rng.random() < r.crate_fraction else _pick(rng, CARTONS)


def fill_shelf(rng, r: Recipe, length: float, depth: float, max_top: float, density: float,
               stack_max: int) -> list[tuple[int, L.Box]]:
    """Place items on one shelf (shelf frame). Returns (category, Box) pairs. Items never
    overlap (slots along x separated by >= min_gap; rows along y separated by >= min_gap),
    stay on the board, stand on the board or on the item below, and stay below max_top."""
    items: list[tuple[int, L.Box]] = []
    margin = 0.02
    yaw_max = math.radians(r.yaw_max_deg)
    x = -length / 2 + margin + float(rng.uniform(0, 0.08))
    misfits = 0
    while misfits < 3:
        cat = _category(rng, r)
        sx, sy, sz = _item_size(rng, r, cat)
        if rng.uniform() < r.turn_fraction:
            sx, sy = sy, sx
        sy = min(sy, depth - 2 * margin)
        if sz > max_top:
            if max_top < 0.08:
                break
            sz = max_top * float(rng.uniform(0.6, 0.95))
        yaw = float(rng.uniform(-yaw_max, yaw_max))
        ex, ey = L.half_extents(sx, sy, yaw)
        if ey * 2 > depth - 2 * margin:
            yaw = 0.0
            ex, ey = L.half_extents(sx, sy, yaw)
        if x + 2 * ex > length / 2 - margin:
            if length / 2 - margin - x < 0.2:
                break
            misfits += 1
            continue  # try another (maybe smaller) item in the remaining space
        slot = (x, x + 2 * ex)
        misfits = 0
        if rng.uniform() < density:
            free = depth - 2 * margin - 2 * ey
            # front row: pushed towards the front edge, with some random set-back (both draws made
            # for either anchor, so that the scenes of the other keys do not depend on it)
            cy = -depth / 2 + margin + ey + float(rng.uniform(0, free)) * float(rng.uniform(0, r.setback))
            if r.box_anchor == "centre":
                cy = 0.0
            base = L.Box(cx=x + ex, cy=cy, sx=sx, sy=sy, sz=sz, z0=0.0, yaw=yaw)
            items.append((cat, base))
            _stack(rng, r, items, cat, base, slot, (-depth / 2 + margin, depth / 2 - margin), max_top, stack_max)
            # optional back row in the same slot
            y_lo = base.y_range()[1] + r.min_gap
            room = depth / 2 - margin - y_lo
            if room > 0.15 and rng.uniform() < r.back_row * density:
                cat2 = cat if rng.uniform() < 0.5 else (_category(rng, r))
                bx, by, bz = _item_size(rng, r, cat2)
                bx, by = min(bx, slot[1] - slot[0]), min(by, room)
                bz = min(bz, max_top * float(rng.uniform(0.6, 0.95)))
                byaw = float(rng.uniform(-yaw_max, yaw_max))
                hx, hy = L.half_extents(bx, by, byaw)
                if 2 * hx > slot[1] - slot[0] or 2 * hy > room:
                    byaw, (hx, hy) = 0.0, (bx / 2, by / 2)
                if bz > 0.05:
                    cx = float(rng.uniform(slot[0] + hx, slot[1] - hx)) if slot[1] - slot[0] > 2 * hx else (slot[0] + slot[1]) / 2
                    cyb = float(rng.uniform(y_lo + hy, depth / 2 - margin - hy)) if room > 2 * hy else y_lo + hy
                    back = L.Box(cx=cx, cy=cyb, sx=bx, sy=by, sz=bz, z0=0.0, yaw=byaw)
                    items.append((cat2, back))
                    _stack(rng, r, items, cat2, back, slot, (y_lo, depth / 2 - margin), max_top, stack_max)
        # the next slot: flush against this one (a wall of cartons) or min_gap and more from it; the
        # flush draw is made only by recipes that use it, so the others keep their scenes
        flush = r.flush_fraction > 0 and rng.uniform() < r.flush_fraction
        x = slot[1] if flush else slot[1] + r.min_gap + float(rng.uniform(0, 0.08))
    return items


def _stack(rng, r, items, cat, base: L.Box, slot, yband, max_top, stack_max):
    """Stack up to stack_max - 1 items on `base`, each no larger than the one below and kept
    inside the slot (x) and the band (y) of its column."""
    height = int(rng.integers(1, stack_max + 1))
    below = base
    for _ in range(height - 1):
        c2 = cat if rng.uniform() < 0.7 else (_pick(rng, CRATES) if cat in CRATES else _pick(rng, CARTONS))
        s = float(rng.uniform(0.85, 1.0))
        sx, sy = below.sx * s, below.sy * s
        sz = _item_size(rng, r, c2)[2]
        z0 = below.z0 + below.sz
        if z0 + sz > max_top:
            sz = max_top - z0
            if sz < 0.08:
                break
        yaw = below.yaw + math.radians(float(rng.uniform(-3, 3)))
        b = L.Box(cx=below.cx, cy=below.cy, sx=sx, sy=sy, sz=sz, z0=z0, yaw=yaw)
        x0, x1 = b.x_range()
        y0, y1 = b.y_range()
        if not (x0 >= slot[0] and x1 <= slot[1] and y0 >= yband[0] - 1e-9 and y1 <= yband[1] + 1e-9):
            b = L.Box(cx=below.cx, cy=below.cy, sx=sx, sy=sy, sz=sz, z0=z0, yaw=below.yaw)
        items.append((c2, b))
        below = b


def _pallet_footprint(rng, depth: float) -> tuple[float, float]:
    """A pallet's (along the beams, across them) size: euro or UK, turned with its long side
    across the beams half the time where the rack is deep enough."""
    along, deep = PALLET_FOOTPRINTS[int(rng.integers(len(PALLET_FOOTPRINTS)))]
    if rng.uniform() < 0.5 and along <= depth + 0.05:   # turned: the long side across the beams
        along, deep = deep, along
    return along, deep


def fitted_bay(rng, r: Recipe, depth: float) -> tuple[float, tuple[float, float, float]]:
    """A pallet bay sized for its pallets (`pallet_bay_fit`): the beam length n * along + (n + 1)
    * gap, for one footprint and clearance, with n the count that keeps the beams within
    `pallet_bay_length` (else the nearest); returns (length, (along, deep, gap))."""
    along, deep = _pallet_footprint(rng, depth)
    gap = _u(rng, r.pallet_gap)
    lo, hi = r.pallet_bay_length
    fits = [n for n in range(1, 9) if lo <= n * along + (n + 1) * gap <= hi]
    if fits:
        n = int(fits[int(rng.integers(len(fits)))])
    else:   # no count fits the range: the count whose bay is nearest to it
        n = min(range(1, 9), key=lambda k: abs(k * along + (k + 1) * gap - (lo + hi) / 2))
    return n * along + (n + 1) * gap, (along, deep, gap)


def fill_pallet_level(rng, r: Recipe, length: float, depth: float, max_top: float,
                      density: float, fit: tuple | None = None) -> list[tuple[str, L.Box, tuple | None]]:
    """Load units on one pallet-rack level (shelf frame): pallets side by side along the beams,
    each slot taken with probability `density`; in a bay sized for its pallets (`fit`, from
    `fitted_bay`: along, deep, gap) every level holds that footprint at that clearance. Returns (load kind, unit Box, the x-ranges of the
    pallets under it where they differ from the unit's, else None) triples; a unit is the pallet(s)
    and its load as one box standing on the level (z0 = 0), as wide as the pallet unless
    `pallet_overhang` widens the load or `pallet_wide_fraction` sets one load on two neighbouring
    pallets, kept on the level (x and y) and below `max_top`."""
    units: list = []
    slots: list[int] = []      # each unit's slot along the beams
    if max_top < PALLET_HEIGHT + 0.2:
        return units
    if fit is None:
        along, deep = _pallet_footprint(rng, depth)
        gap = _u(rng, r.pallet_gap)
    else:
        along, deep, gap = fit
    deep = min(deep, depth - 0.02)
    # a bay sized for its pallets holds n of them exactly (round: no float error drops one)
    n = int((length - gap) // (along + gap)) if fit is None else max(1, round((length - gap) / (along + gap)))
    if n < 1:
        along, n = length - 2 * gap, 1
    pitch = length / n
    # packed: neighbours stand `gap` apart and the row sits anywhere along the beams (a bay sized
    # for its pallets, gaps of a hand's width); spread: one pallet per 1/n of the beam
    packed = r.pallet_packing > 0 and rng.uniform() < r.pallet_packing
    if packed:
        pitch = along + gap
        start = -length / 2 + float(rng.uniform(0, max(0.0, length - n * along - (n - 1) * gap))) - gap / 2
    for k in range(n):
        if rng.uniform() >= density:
            continue
        kind = rng.choice(list(r.pallet_load), p=list(r.pallet_load.values()))
        if packed:
            cx = start + pitch * (k + 0.5) + float(rng.uniform(-0.15, 0.15)) * gap
            cx = min(max(cx, -length / 2 + along / 2), length / 2 - along / 2)
        else:
            cx = -length / 2 + pitch * (k + 0.5) + float(rng.uniform(-0.25, 0.25)) * (pitch - along)
        cy = -depth / 2 + 0.01 + deep / 2 + float(rng.uniform(0, max(0.0, depth - 0.02 - deep)))
        sz = PALLET_HEIGHT + _u(rng, r.pallet_load_height) * (max_top - PALLET_HEIGHT)
        units.append((kind, L.Box(cx=cx, cy=cy, sx=along, sy=deep, sz=sz, z0=0.0, yaw=0.0), None))
        slots.append(k)
    if r.pallet_wide_fraction > 0:    # drawn only by recipes that use them: the others keep their scenes
        units = _wide_loads(rng, r, units, slots, length)
    if r.pallet_overhang[1] > 0:
        units = _overhang(rng, r, units, length)
    return units


def _room(placed: list, following: list, length: float) -> tuple[float, float]:
    """The stretch of beam a unit may take: from the last placed unit's right edge (else the
    beams' left end) to the next unit's left edge (else the right end)."""
    lo = placed[-1][1].cx + placed[-1][1].sx / 2 if placed else -length / 2
    hi = following[0][1].cx - following[0][1].sx / 2 if following else length / 2
    return lo, hi


def _wide_loads(rng, r: Recipe, units: list, slots: list, length: float) -> list:
    """Loads wider than a pallet standing on two (long crates, appliance cartons, flat-packed
    boards): each pair of loads in neighbouring slots becomes, with probability
    `pallet_wide_fraction`, one load on both pallets, the pallets moved together (0-5 cm apart)
    about the pair's middle, never onto a neighbour; the load is as wide as the two pallets and
    as deep and as tall as the larger of the two. `units` holds (kind, Box, None) triples and
    `slots` their slots along the beams; merged units carry their two pallets' x-ranges
    ((x0, x1), (x0, x1)) in place of None."""
    out, i = [], 0
    while i < len(units):
        kind, a, _ = units[i]
        if i + 1 < len(units) and slots[i + 1] == slots[i] + 1 and rng.uniform() < r.pallet_wide_fraction:
            b = units[i + 1][1]
            lo, hi = _room(out, units[i + 2:], length)    # never onto a neighbour
            gap = min(float(rng.uniform(0.0, 0.05)), max(0.0, hi - lo - a.sx - b.sx))
            width = a.sx + b.sx + gap
            cx = min(max((a.cx + b.cx) / 2, lo + width / 2), hi - width / 2)
            x0 = cx - width / 2
            pallets = ((x0, x0 + a.sx), (x0 + a.sx + gap, x0 + width))
            out.append((kind, L.Box(cx=cx, cy=a.cy, sx=width, sy=max(a.sy, b.sy), sz=max(a.sz, b.sz), z0=0.0,
                                    yaw=0.0), pallets))
            i += 2
            continue
        out.append(units[i])
        i += 1
    return out


def _overhang(rng, r: Recipe, units: list, length: float) -> list:
    """Loads wider than their pallet (cartons or a wrapped load overhanging it along the beams):
    each unit widened by up to `pallet_overhang` on each side, never past the beams' ends or a
    neighbour's (possibly widened) edge; the unit keeps its pallets' x-ranges (drawn under it)."""
    out = []
    for i, (kind, b, pallets) in enumerate(units):
        lo_lim, hi_lim = _room(out, units[i + 1:], length)
        x0, x1 = b.cx - b.sx / 2, b.cx + b.sx / 2
        x0 = max(lo_lim, x0 - _u(rng, r.pallet_overhang))
        x1 = min(hi_lim, x1 + _u(rng, r.pallet_overhang))
        out.append((kind, L.Box(cx=(x0 + x1) / 2, cy=b.cy, sx=x1 - x0, sy=b.sy, sz=b.sz, z0=b.z0, yaw=b.yaw),
                    pallets or ((b.cx - b.sx / 2, b.cx + b.sx / 2),)))
    return out


def fill_cube_row(rng, r: Recipe, columns: int, cell: float, panel: float, depth: float, max_top: float,
                  density: float) -> list[tuple[int, L.Box]]:
    """Items in one row of a cube unit (shelf frame; the row's floor panel is the board): each
    cell, taken with probability `density`, holds one bin filling most of it (`cube_bin`) or 1-4
    small items side by side. Everything stays inside its cell (x: between the panels; y: on the
    panel) and below `max_top`, so neighbouring cells' loads are a panel's width apart at least."""
    items: list[tuple[int, L.Box]] = []
    length = columns * cell + (columns + 1) * panel
    for j in range(columns):
        if rng.uniform() >= density:
            continue
        x0 = -length / 2 + panel + j * (cell + panel)
        if rng.uniform() < r.cube_bin:
            cat = _pick(rng, CRATES) if rng.uniform() < 0.4 else _pick(rng, CARTONS)
            sx = cell - float(rng.uniform(0.01, 0.04))
            sy = min(depth - 0.01, depth * float(rng.uniform(0.75, 0.97)))
            sz = min(max_top, cell * float(rng.uniform(0.7, 0.95)))
            cx = x0 + cell / 2 + float(rng.uniform(-0.5, 0.5)) * (cell - sx)
            cy = -depth / 2 + 0.005 + sy / 2 + float(rng.uniform(0, 0.3)) * (depth - 0.01 - sy)
            items.append((cat, L.Box(cx=cx, cy=cy, sx=sx, sy=sy, sz=sz)))
            continue
        x = x0 + float(rng.uniform(0.0, 0.03))
        for _ in range(int(rng.integers(1, 5))):
            sx = float(rng.uniform(0.04, 0.15))
            if x + sx > x0 + cell:
                break
            sy = float(rng.uniform(0.08, min(0.3, depth - 0.01)))
            sz = float(rng.uniform(0.03, min(0.25, max_top)))
            cy = -depth / 2 + 0.005 + sy / 2 + float(rng.uniform(0, 0.5)) * (depth - 0.01 - sy)
            items.append((_pick(rng, CARTONS), L.Box(cx=x + sx / 2, cy=cy, sx=sx, sy=sy, sz=sz)))
            x += sx + r.min_gap + float(rng.uniform(0.0, 0.04))
    return items


# --- the scene ------------------------------------------------------------------------------
class _Builder:
    def __init__(self, rng, r: Recipe):
        self.rng, self.r, self.objects = rng, r, []
        self.board_tint = None   # a scene colour for every board (palette_random), else per-board jitter
        self.label_size = None   # (width, height) of the location labels on front beams (beam_labels), else none
        self.collect = None      # per level: where a neighbouring bay's items go as layout boxes (layout_extent 'row')
        self.pallet_fit = None   # (along, deep, gap) of the pallets every level of a bay sized for them holds (pallet_bay_fit)

    def collected(self, si: int, boxes, x0: float, y0: float) -> None:
        """Record a neighbouring bay's level-`si` items in the considered bay's frame (no draw)."""
        if self.collect is not None:
            self.collect[si].extend(replace(b, cx=b.cx + x0, cy=b.cy + y0) for b in boxes)

    def add(self, center, size, material, semantic, yaw=0.0, tint=None, shape="box", **kw) -> int:
        tint = tint if tint is not None else _tint(self.rng, self.r.tint_jitter)
        self.objects.append(Obj((float(center[0]), float(center[1]), float(center[2])),
                                (float(size[0]), float(size[1]), float(size[2])), float(yaw),
                                material, semantic, tint, shape, **kw))
        return len(self.objects) - 1

    def item(self, cat: int, box: L.Box, z_board: float, x_off=0.0, y_off=0.0, shelf=-1, keep_layout=False):
        mat = CATEGORY_NAMES[cat]
        sem = SEM["crate"] if cat in CRATES else SEM["box"]
        return self.add((box.cx + x_off, box.cy + y_off, z_board + box.z0 + box.sz / 2), (box.sx, box.sy, box.sz),
                        mat, sem, yaw=box.yaw, category=cat, shelf=shelf,
                        layout_box=box if keep_layout else None)

    def place_items(self, items, si: int, z_top: float, x0: float, y0: float, shelf_infos=None) -> None:
        """Add one level's (category, Box) items to the bay centred at (x0, y0), standing on its
        board top `z_top`; in the considered bay (`shelf_infos` given) they are shelf `si`'s items."""
        mine = shelf_infos is not None
        idx = [self.item(cat, b, z_top, x0, y0, shelf=si if mine else -1, keep_layout=mine) for cat, b in items]
        if mine:
            shelf_infos[si].items = idx
        else:
            self.collected(si, [b for _, b in items], x0, y0)

    def level_density(self, mine: bool) -> float:
        """One level's load density: box_density's draw, raised by `neighbour_fill` in every bay
        but the considered one (`mine`)."""
        d, f = _u(self.rng, self.r.box_density), self.r.neighbour_fill
        return d if mine or f == 0 else f + (1 - f) * d

    def shelf_items(self, boards, length, depth, x0, y0, shelf_infos=None) -> None:
        """Cartons and crates straight on every level of a shelving-like bay (shelving, wire and
        boltless units): each level's density and stack height drawn, then `fill_shelf`."""
        r = self.r
        for si, (z_top, _h, max_top) in enumerate(boards):
            density = self.level_density(shelf_infos is not None)
            stack_max = _ui(self.rng, r.max_stack)
            self.place_items(fill_shelf(self.rng, r, length, depth, max_top, density, stack_max),
                             si, z_top, x0, y0, shelf_infos)

    def location_labels(self, x0, y_front, length, z_beam, beam_h) -> None:
        """Location labels on a front beam whose front face is at `y_front`, centred at height
        `z_beam`: about one per metre of beam, evenly spaced with a little jitter, when the
        scene has them (`label_size`). Rack structure, like the beam."""
        if self.label_size is None:
            return
        w, h = self.label_size
        h = min(h, 0.8 * beam_h)
        n = max(1, int(length / 1.0))
        for k in range(n):
            cx = x0 - length / 2 + (k + 0.5) * length / n + float(self.rng.uniform(-0.05, 0.05))
            self.add((cx, y_front - 0.0015, z_beam), (w, 0.002, h), "beam_label", SEM["rack"], tint=(1.0, 1.0, 1.0))

    def uprights(self, x0, y0, length, depth, top_z, tint, which=(True, True), frame=False):
        """The uprights of a bay centred at (x0, y0), front and back, on the sides `which` says
        (left, right; a side shared with the neighbouring bay is drawn once). `frame`: pallet
        racking's footplates and the horizontal braces of each side frame too."""
        uw = self.r.upright_width
        for side, want in zip((-1, 1), which):
            if not want:
                continue
            xs = x0 + side * (length / 2 + uw / 2)
            for yy in (-1, 1):
                ys = y0 + yy * (depth / 2 - uw / 2)
                self.add((xs, ys, top_z / 2), (uw, uw, top_z), "steel", SEM["rack"], tint=tint)
                if frame:
                    self.add((xs, ys, 0.004), (uw + 0.06, uw + 0.06, 0.008), "steel", SEM["rack"], tint=tint)
            if frame:
                for zb in np.arange(0.3, top_z - 0.2, 1.1):
                    self.add((xs, y0, float(zb)), (0.03, depth - 2 * uw, 0.04), "steel", SEM["rack"], tint=tint)

    def rack(self, x0, y0, length, depth, boards, beam_h, top_z, steel_tint, beam_tint, filled,
             shelf_infos=None, uprights=(True, True)):
        """A rack bay centred at (x0, y0): uprights, beams, boards and (optionally) items."""
        r = self.r
        self.uprights(x0, y0, length, depth, top_z, steel_tint, uprights)
        for zi, (z_top, _h, _mt) in enumerate(boards):
            t = r.board_thickness
            self.add((x0, y0, z_top - t / 2), (length, depth, t), "board", SEM["shelf"],
                     tint=None if self.board_tint is None else _tint(self.rng, 0.05, self.board_tint))
            for yy in (-1, 1):
                self.add((x0, y0 + yy * (depth / 2 - 0.025), z_top - t - beam_h / 2), (length, 0.05, beam_h),
                         "beam", SEM["rack"], tint=beam_tint)
            self.location_labels(x0, y0 - depth / 2, length, z_top - t - beam_h / 2, beam_h)
        if filled:
            self.shelf_items(boards, length, depth, x0, y0, shelf_infos)

    def pallet_rack(self, x0, y0, length, depth, boards, beam_h, top_z, steel_tint, beam_tint, deck,
                    shelf_infos=None, uprights=(True, True)):
        """A pallet-rack bay centred at (x0, y0): perforated uprights with footplates and side-frame
        braces, a beam pair under every level off the floor (a wire deck on them where `deck`),
        and load units on pallets, or, on some wire-deck levels, cartons and crates straight on
        the deck. A level whose board top is 0 is the floor position."""
        r = self.r
        self.uprights(x0, y0, length, depth, top_z, steel_tint, uprights, frame=True)
        for z_top, _h, _mt in boards:
            if z_top <= 0:
                continue   # the floor position: no beams
            for yy in (-1, 1):
                self.add((x0, y0 + yy * (depth / 2 - 0.03), z_top - beam_h / 2), (length, 0.06, beam_h),
                         "beam", SEM["rack"], tint=beam_tint)
            self.location_labels(x0, y0 - depth / 2, length, z_top - beam_h / 2, beam_h)
            if deck:   # sits in the beams' step, 2 mm below their tops, which carry the pallets
                self.add((x0, y0, z_top - 0.007), (length, depth - 0.02, 0.01), "deck", SEM["shelf"], tint=(1, 1, 1))
        shelf_of = (lambda si: si) if shelf_infos is not None else (lambda si: -1)
        for si, (z_top, _h, max_top) in enumerate(boards):
            density = self.level_density(shelf_infos is not None)
            if deck and z_top > 0 and self.rng.uniform() < DECK_LOOSE:
                # cartons and crates straight on the wire deck, as on shelving
                self.place_items(fill_shelf(self.rng, r, length, depth, max_top, density, _ui(self.rng, r.max_stack)),
                                 si, z_top, x0, y0, shelf_infos)
                continue
            units = fill_pallet_level(self.rng, r, length, depth, max_top, density, self.pallet_fit)
            idx = [self.pallet_unit(kind, b, z_top, x0, y0, shelf_of(si), detailed=shelf_infos is not None,
                                    pallets=pallets) for kind, b, pallets in units]
            if shelf_infos is not None:
                shelf_infos[si].items = idx
            else:
                self.collected(si, [b for _, b, _ in units], x0, y0)

    def cube_unit(self, x0, y0, length, depth, boards, columns, cell, panel, tint, back,
                  shelf_infos=None):
        """A cube unit centred at (x0, y0): a floor panel under every row (the shelf boards), a
        top panel, two side panels and a divider between neighbouring cells (all `panel` thick),
        a back panel where `back`, and items in the cells."""
        r = self.r
        top = boards[-1][0] + boards[-1][1]
        for z_top, _h, _mt in boards:
            self.add((x0, y0, z_top - panel / 2), (length, depth, panel), "board", SEM["shelf"], tint=tint)
        self.add((x0, y0, top - panel / 2), (length, depth, panel), "board", SEM["rack"], tint=tint)
        z_lo = boards[0][0] - panel
        for j in range(columns + 1):
            xs = x0 - length / 2 + panel / 2 + j * (cell + panel)
            self.add((xs, y0, (z_lo + top) / 2), (panel, depth, top - z_lo), "board", SEM["rack"], tint=tint)
        if back:
            self.add((x0, y0 + depth / 2 + 0.003, (z_lo + top) / 2), (length, 0.006, top - z_lo), "board",
                     SEM["rack"], tint=tint)
        for si, (z_top, _h, max_top) in enumerate(boards):
            self.place_items(fill_cube_row(self.rng, r, columns, cell, panel, depth, max_top,
                                           self.level_density(shelf_infos is not None)),
                             si, z_top, x0, y0, shelf_infos)

    def wire_unit(self, x0, y0, length, depth, boards, tint, pitch, shelf_infos=None):
        """A wire-shelving unit centred at (x0, y0): four round posts just outside the decks'
        corners and a deck at every board top, cartons and crates on it. The considered unit's
        decks are drawn wire by wire (wires front to back every `pitch`, tops at the board top,
        two support wires along it, a frame band WIRE_TRUSS tall at the front and back); the
        neighbours' as one mesh-textured slab. Wires are shelf, posts and frames rack structure."""
        detailed = shelf_infos is not None
        top = boards[-1][0] + 0.04
        for sx in (-1, 1):
            for sy in (-1, 1):
                self.add((x0 + sx * (length / 2 + WIRE_POST / 2), y0 + sy * (depth / 2 - WIRE_POST / 2), top / 2),
                         (WIRE_POST, WIRE_POST, top), "chrome", SEM["rack"], tint=tint, shape="cylinder")
        for z_top, _h, _mt in boards:
            for sy in (-1, 1):
                self.add((x0, y0 + sy * (depth / 2 - 0.004), z_top - WIRE_TRUSS / 2), (length, 0.008, WIRE_TRUSS),
                         "chrome", SEM["rack"], tint=tint)
            if not detailed:
                self.add((x0, y0, z_top - 0.003), (length, depth - 0.016, 0.006), "deck", SEM["shelf"], tint=tint)
                continue
            n = max(2, int(round(length / pitch)))
            for k in range(n + 1):
                self.add((x0 - length / 2 + 0.002 + k * (length - 0.004) / n, y0, z_top - 0.002),
                         (0.004, depth - 0.016, 0.004), "chrome", SEM["shelf"], tint=tint)
            for f in (-0.25, 0.25):
                self.add((x0, y0 + f * depth, z_top - 0.006), (length, 0.004, 0.004), "chrome", SEM["shelf"], tint=tint)
        self.shelf_items(boards, length, depth, x0, y0, shelf_infos)

    def boltless_unit(self, x0, y0, length, depth, boards, beam_h, top_z, tint, steel_deck, shelf_infos=None,
                      uprights=(True, True)):
        """A boltless-shelving bay centred at (x0, y0): an angle post (two perforated flanges) at
        each corner, on the sides `uprights` says (a post shared with the neighbouring bay is drawn
        once); at every level a beam on each side framing the deck, its top BOLTLESS_LIP above the
        deck top; the deck chipboard or, where `steel_deck`, a steel panel with ribs under it.
        Decks are shelf, posts and beams rack structure; cartons and crates on the decks."""
        a, t = BOLTLESS_ANGLE, BOLTLESS_PLATE
        self.angle_posts(x0, y0, length, depth, top_z, tint, uprights, "steel")
        for z_top, _h, _mt in boards:
            zb = z_top + BOLTLESS_LIP - beam_h / 2
            for yy in (-1, 1):
                self.add((x0, y0 + yy * (depth / 2 - t / 2), zb), (length, t, beam_h), "beam", SEM["rack"], tint=tint)
            self.location_labels(x0, y0 - depth / 2, length, zb, beam_h)
            for side in (-1, 1):
                self.add((x0 + side * (length / 2 + t / 2), y0, zb), (t, depth - 2 * a, beam_h), "beam", SEM["rack"],
                         tint=tint)
            if steel_deck:
                self.add((x0, y0, z_top - t / 2), (length, depth - 2 * t, t), "paint", SEM["shelf"], tint=tint)
                for f in (-0.3, 0.0, 0.3):
                    self.add((x0, y0 + f * depth, z_top - t - BOLTLESS_RIB / 2), (length, 0.01, BOLTLESS_RIB), "paint",
                             SEM["rack"], tint=tint)
            else:
                bt = BOLTLESS_BOARD
                self.add((x0, y0, z_top - bt / 2), (length, depth - 2 * t, bt), "board", SEM["shelf"],
                         tint=None if self.board_tint is None else _tint(self.rng, 0.05, self.board_tint))
        self.shelf_items(boards, length, depth, x0, y0, shelf_infos)

    def angle_posts(self, x0, y0, length, depth, top_z, tint, uprights, material) -> None:
        """An angle post (two flanges BOLTLESS_ANGLE wide, BOLTLESS_PLATE thick) at each corner of
        a shelving bay centred at (x0, y0), just outside its length, on the sides `uprights` says
        (a post shared with the neighbouring bay is drawn once)."""
        a, t = BOLTLESS_ANGLE, BOLTLESS_PLATE
        for side, want in zip((-1, 1), uprights):
            if not want:
                continue
            for yy in (-1, 1):
                self.add((x0 + side * (length / 2 + a / 2), y0 + yy * (depth / 2 - t / 2), top_z / 2), (a, t, top_z),
                         material, SEM["rack"], tint=tint)
                self.add((x0 + side * (length / 2 + a - t / 2), y0 + yy * (depth / 2 - a / 2), top_z / 2),
                         (t, a, top_z), material, SEM["rack"], tint=tint)

    def slotted_unit(self, x0, y0, length, depth, boards, lip, top_z, tint, steel_deck, shelf_infos=None,
                     uprights=(True, True)):
        """A slotted-angle shelving bay centred at (x0, y0): an angle post punched with slots and
        holes at each corner (shared with the neighbouring bay), and at every level either a
        steel panel whose edges fold down `lip` on all four sides (`steel_deck`) or a chipboard
        deck on a frame of angles whose upright flanges (`lip` tall) show under its front and
        back. Panels and decks are shelf; lips, frames and posts rack structure. No beam rises
        above a deck (unlike boltless shelving). Cartons and crates on the decks."""
        t = BOLTLESS_PLATE
        self.angle_posts(x0, y0, length, depth, top_z, tint, uprights, "slotted")
        for z_top, _h, _mt in boards:
            top = SLOTTED_PLATE if steel_deck else BOLTLESS_BOARD
            if steel_deck:
                self.add((x0, y0, z_top - top / 2), (length, depth, top), "paint", SEM["shelf"], tint=tint)
            else:
                self.add((x0, y0, z_top - top / 2), (length, depth, top), "board", SEM["shelf"],
                         tint=None if self.board_tint is None else _tint(self.rng, 0.05, self.board_tint))
            zl = z_top - top - lip / 2
            for yy in (-1, 1):   # front and back lips (or frame flanges), flush with the deck's edges
                self.add((x0, y0 + yy * (depth / 2 - t / 2), zl), (length, t, lip), "paint", SEM["rack"], tint=tint)
            if steel_deck:
                for side in (-1, 1):
                    self.add((x0 + side * (length / 2 - t / 2), y0, zl), (t, depth - 2 * t, lip), "paint", SEM["rack"],
                             tint=tint)
            self.location_labels(x0, y0 - depth / 2, length, zl, lip)
        self.shelf_items(boards, length, depth, x0, y0, shelf_infos)

    def pallet_unit(self, kind: str, b: L.Box, z_board: float, x_off: float, y_off: float, shelf: int,
                    detailed: bool, pallets: tuple | None = None) -> int:
        """One load unit: an undrawn object holding the unit's box (what the ground truth
        sees), its pallets (their x-ranges `pallets`, default one as wide as the unit) and its load
        drawn as parts of it. A carton or crate load is drawn as single cartons/crates, fewer of
        them in background bays (not `detailed`)."""
        rng = self.rng
        cx, cy = b.cx + x_off, b.cy + y_off
        unit = self.add((cx, cy, z_board + b.sz / 2), (b.sx, b.sy, b.sz), "pallet",
                        SEM["crate"] if kind == "crates" else SEM["box"],
                        shape="none", category=PALLET_UNITS[kind], shelf=shelf,
                        layout_box=b if shelf >= 0 else None)
        for p0, p1 in pallets or ((b.cx - b.sx / 2, b.cx + b.sx / 2),):
            self.add(((p0 + p1) / 2 + x_off, cy, z_board + PALLET_HEIGHT / 2), (p1 - p0, b.sy, PALLET_HEIGHT),
                     "pallet", SEM["pallet"], part_of=unit)
        h = b.sz - PALLET_HEIGHT
        inset = float(rng.uniform(0.0, 0.05))
        lx, ly = b.sx - 2 * inset, b.sy - 2 * inset
        z0 = z_board + PALLET_HEIGHT
        if kind == "wrapped":
            self.add((cx, cy, z0 + h / 2), (lx, ly, h), "wrap", SEM["box"], part_of=unit)
            return unit
        cat = _pick(rng, CRATES) if kind == "crates" else _pick(rng, CARTONS)
        csx, csy, csz = _item_size(rng, self.r, cat)
        cap = (4, 4, 6) if detailed else (3, 2, 3)
        nx, ny, nz = (min(c, max(1, round(a / b))) for c, a, b in zip(cap, (lx, ly, h), (csx, csy, csz)))
        sx, sy, sz = lx / nx, ly / ny, h / nz
        sem = SEM["crate"] if kind == "crates" else SEM["box"]
        for iz in range(nz):
            for ix in range(nx):
                for iy in range(ny):
                    self.add((cx - lx / 2 + (ix + 0.5) * sx, cy - ly / 2 + (iy + 0.5) * sy, z0 + (iz + 0.5) * sz),
                             (sx - 0.004, sy - 0.004, sz - 0.002), CATEGORY_NAMES[cat], sem, part_of=unit)
        return unit


def _depth_range(r: Recipe, style: str) -> tuple[float, float]:
    """The recipe's rack depth range (m) for a rack style."""
    return {"pallet": r.pallet_rack_depth, "cube": r.cube_depth, "wire": r.wire_depth}.get(style, r.rack_depth)


def sample_scene(r: Recipe, seed: int, index: int, max_camera_tries: int = 60) -> Scene:
    """Sample the scene of image `index`; deterministic in (recipe, seed, index)."""
    rng = scene_rng(seed, index)
    B = _Builder(rng, r)

    # the considered rack; the style is drawn only when a style other than shelving has a weight,
    # so recipes without one keep their scenes draw for draw
    style, deck, steel_deck = "shelving", False, False
    if any(w > 0 for k, w in r.rack_style.items() if k != "shelving"):
        w = np.array(list(r.rack_style.values()))
        style = str(rng.choice(list(r.rack_style), p=w / w.sum()))
    # a tall view as a photo of a tall rack (tall_view_shelves): drawn with the rack, so the other
    # racks keep n_shelves; None: the key is off and the camera draws its own tall view; recipes
    # without the key draw no extra number
    tall_rack = None
    if r.tall_view_shelves[1] > 0:
        tall_rack = (r.tall_view_fraction > 0 and style in ("shelving", "boltless", "slotted")
                     and bool(rng.random() < r.tall_view_fraction))
    n_range = r.tall_view_shelves if tall_rack else r.n_shelves
    boards = []
    if style == "cube":
        columns, rows = _ui(rng, r.cube_columns), _ui(rng, r.cube_rows)
        cell, depth = _u(rng, r.cube_cell), _u(rng, _depth_range(r, style))
        panel = float(rng.uniform(0.015, 0.035))
        length = columns * cell + (columns + 1) * panel
        cube_back = bool(rng.uniform() < 0.5)
        z = float(rng.uniform(0.0, 0.1)) + panel     # on the floor or on short feet
        for _ in range(rows):
            boards.append((z, cell + panel, cell - 0.005))
            z += cell + panel
    elif style == "wire":
        length, depth = _u(rng, r.wire_length), _u(rng, _depth_range(r, style))
        n, h_nom = _ui(rng, r.wire_levels), _u(rng, r.wire_level_height)
        wire_pitch = float(rng.uniform(0.02, 0.035))
        z = float(rng.uniform(0.1, 0.25))     # the lowest deck, above the posts' feet
        for i in range(n):
            h = h_nom * (1 + float(rng.uniform(-r.shelf_height_jitter, r.shelf_height_jitter)))
            # loads stay under the next deck's frame; the top deck is open above
            boards.append((z, h, h - WIRE_TRUSS - 0.02 if i < n - 1 else h - 0.02))
            z += h
    elif style == "pallet":
        length, depth = _u(rng, r.pallet_bay_length), _u(rng, _depth_range(r, style))
        # drawn only when the knob is on, so recipes without it keep their scenes draw for draw
        if r.pallet_bay_fit > 0 and rng.uniform() < r.pallet_bay_fit:
            length, B.pallet_fit = fitted_bay(rng, r, depth)
        n = _ui(rng, r.pallet_levels)
        h_nom = _u(rng, r.pallet_level_height)
        beam_h = float(rng.uniform(0.1, 0.16))
        z = 0.0 if rng.uniform() < r.floor_level else float(rng.uniform(0.1, 0.25))
        deck = bool(rng.uniform() < r.wire_deck)
        for i in range(n):
            h = h_nom * (1 + float(rng.uniform(-r.shelf_height_jitter, r.shelf_height_jitter)))
            # forklift clearance under the next beam; the top level ends at the uprights' top
            boards.append((z, h, h - beam_h - 0.1 if i < n - 1 else h - 0.1))
            z += h
    elif style == "boltless":   # the shelving keys size it; its own construction and finishes
        length, depth = _u(rng, r.rack_length), _u(rng, _depth_range(r, style))
        n = _ui(rng, n_range)
        h_nom = _u(rng, r.shelf_height)
        beam_h = float(rng.uniform(0.035, 0.09))
        steel_deck = bool(rng.uniform() < 0.5)
        z = float(rng.uniform(0.04, 0.15))
        # loads stay under the next level's beams and deck (and its ribs); the top level is open
        under = max(beam_h - BOLTLESS_LIP, BOLTLESS_PLATE + BOLTLESS_RIB if steel_deck else BOLTLESS_BOARD)
        for i in range(n):
            h = h_nom * (1 + float(rng.uniform(-r.shelf_height_jitter, r.shelf_height_jitter)))
            boards.append((z, h, h - under - 0.02 if i < n - 1 else h - 0.05))
            z += h
    elif style == "slotted":    # the shelving keys size it; panels or chipboard on angle frames
        length, depth = _u(rng, r.rack_length), _u(rng, _depth_range(r, style))
        n = _ui(rng, n_range)
        h_nom = _u(rng, r.shelf_height)
        beam_h = float(rng.uniform(0.025, 0.045))    # the lip under each deck
        steel_deck = bool(rng.uniform() < 0.6)
        z = float(rng.uniform(0.03, 0.12))
        under = beam_h + (SLOTTED_PLATE if steel_deck else BOLTLESS_BOARD)
        for i in range(n):
            h = h_nom * (1 + float(rng.uniform(-r.shelf_height_jitter, r.shelf_height_jitter)))
            boards.append((z, h, h - under - 0.02 if i < n - 1 else h - 0.05))
            z += h
    else:
        length, depth = _u(rng, r.rack_length), _u(rng, _depth_range(r, style))
        n = _ui(rng, n_range)
        h_nom = _u(rng, r.shelf_height)
        beam_h = _u(rng, r.beam_height)
        z = _u(rng, r.bottom_height)
        for i in range(n):
            h = h_nom * (1 + float(rng.uniform(-r.shelf_height_jitter, r.shelf_height_jitter)))
            below_next = h - r.board_thickness - beam_h - 0.03 if i < n - 1 else h - 0.05
            boards.append((z, h, max(below_next, 0.0)))
            z += h
    top_z = boards[-1][0] + boards[-1][1]  # uprights end one nominal height above the top board
    shelves = [ShelfInfo(board_top=b[0], clear_height=b[1], max_item_top=b[2]) for b in boards]
    steel_tint = _tint(rng, 0.15, (0.25, 0.35, 0.65) if rng.uniform() < 0.6 else (0.55, 0.56, 0.58))
    beam_tint = _tint(rng, 0.1, (0.95, 0.45, 0.08) if rng.uniform() < 0.7 else (0.2, 0.3, 0.7))
    if style == "cube":   # white, black or wood-effect panels
        steel_tint = _tint(rng, 0.06, ((0.92, 0.92, 0.9), (0.13, 0.12, 0.12), (0.78, 0.62, 0.45))[int(rng.integers(3))])
    elif style == "wire":
        finish = rng.choice(range(len(WIRE_FINISHES)), p=[w for _, w in WIRE_FINISHES])
        steel_tint = _tint(rng, 0.04, WIRE_FINISHES[finish][0])
    elif style == "boltless":   # one colour for posts, beams and steel decks
        finish = rng.choice(range(len(BOLTLESS_FINISHES)), p=[w for _, w in BOLTLESS_FINISHES])
        steel_tint = _tint(rng, 0.06, BOLTLESS_FINISHES[finish][0])
    elif style == "slotted":
        finish = rng.choice(range(len(SLOTTED_FINISHES)), p=[w for _, w in SLOTTED_FINISHES])
        steel_tint = _tint(rng, 0.06, SLOTTED_FINISHES[finish][0])
    board_tint = wall_base = None
    # drawn only when the knob is on, so recipes without it keep their scenes draw for draw
    if r.palette_random > 0 and rng.uniform() < r.palette_random:
        steel_tint, board_tint, wall_base = _random_colour(rng), _random_colour(rng), _random_colour(rng, 0.4)
        beam_tint = steel_tint if rng.uniform() < 0.5 else _random_colour(rng)   # one-colour shelving
        B.board_tint = board_tint

    # location labels on the front beams; drawn only when the knob is on (other recipes keep their scenes)
    if r.beam_labels > 0 and style in ("shelving", "pallet", "boltless", "slotted") and rng.uniform() < r.beam_labels:
        B.label_size = (float(rng.uniform(0.08, 0.2)), float(rng.uniform(0.03, 0.08)))

    background = rng.choice(list(r.background), p=list(r.background.values()))
    corridor = _u(rng, r.corridor_width)
    ceiling = _u(rng, r.ceiling_height)

    # occupancy map at bay granularity: rows (y) x bays (x); the considered bay is at row 0, col K
    K = r.bays_per_side if background == "busy" else 0
    # bay pitch: wire units stand apart on their own posts; boltless and slotted-angle bays share their angle posts
    pitch_x = length + {"wire": 2 * WIRE_POST + 0.005, "boltless": BOLTLESS_ANGLE,
                        "slotted": BOLTLESS_ANGLE}.get(style, r.upright_width)
    rows_y = [0.0]
    depths = [depth]
    occ = []
    if background == "busy":
        y_back = depth / 2
        for row in range(1, r.rack_rows + 1):
            d2 = depth if row % 2 else _u(rng, _depth_range(r, style))
            # back-to-back rows pair up (small flue gap), pairs are separated by corridors
            gap = float(rng.uniform(0.1, 0.3)) if row % 2 else _u(rng, r.corridor_width)
            rows_y.append(y_back + gap + d2 / 2)
            depths.append(d2)
            y_back = rows_y[-1] + d2 / 2
        far_wall = y_back + float(rng.uniform(1.5, 4.0))
    else:
        far_wall = depth / 2 + _u(rng, r.wall_gap)
    for ri, (yc, d2) in enumerate(zip(rows_y, depths)):
        row = []
        for col in range(-K, K + 1):
            occupied = (ri == 0 and col == 0) or (background == "busy" and rng.uniform() < r.rack_density)
            row.append(occupied)
        occ.append(row)

    # the considered bay's row as far as its bays stand side by side, sharing uprights (layout_extent 'row')
    run = (0, 0)
    if r.layout_extent == "row" and style in ROW_STYLES:
        lo_c = hi_c = K
        while lo_c > 0 and occ[0][lo_c - 1]:
            lo_c -= 1
        while hi_c < 2 * K and occ[0][hi_c + 1]:
            hi_c += 1
        run = (lo_c - K, hi_c - K)
    row_boxes = [[] for _ in boards] if run != (0, 0) else None

    # racks: uprights are shared between neighbouring bays of a row
    for ri, (yc, d2) in enumerate(zip(rows_y, depths)):
        row = occ[ri]
        for ci, col in enumerate(range(-K, K + 1)):
            if not row[ci]:
                continue
            left_shared = ci > 0 and row[ci - 1]
            is_target = ri == 0 and col == 0
            B.collect = row_boxes if ri == 0 and run[0] <= col <= run[1] and not is_target else None
            if style == "cube":
                B.cube_unit(col * pitch_x, yc, length, d2, boards, columns, cell, panel, steel_tint, cube_back,
                            shelf_infos=shelves if is_target else None)
            elif style == "wire":
                B.wire_unit(col * pitch_x, yc, length, d2, boards, steel_tint, wire_pitch,
                            shelf_infos=shelves if is_target else None)
            elif style == "boltless":
                B.boltless_unit(col * pitch_x, yc, length, d2, boards, beam_h, top_z, steel_tint, steel_deck,
                                shelf_infos=shelves if is_target else None, uprights=(not left_shared, True))
            elif style == "slotted":
                B.slotted_unit(col * pitch_x, yc, length, d2, boards, beam_h, top_z, steel_tint, steel_deck,
                               shelf_infos=shelves if is_target else None, uprights=(not left_shared, True))
            elif style == "pallet":
                B.pallet_rack(col * pitch_x, yc, length, d2, boards, beam_h, top_z, steel_tint, beam_tint, deck,
                              shelf_infos=shelves if is_target else None, uprights=(not left_shared, True))
            else:
                B.rack(col * pitch_x, yc, length, d2, boards, beam_h, top_z, steel_tint, beam_tint, filled=True,
                       shelf_infos=shelves if is_target else None, uprights=(not left_shared, True))
    B.collect = None

    # building: floor, ceiling, walls, lamps
    fl_tint = _tint(rng, 0.12)
    B.add((0, far_wall / 2, -0.05), (80, 80 + far_wall, 0.1), "concrete", SEM["floor"], tint=fl_tint)
    B.add((0, 0, ceiling + 0.1), (80, 120, 0.2), "ceiling", SEM["wall"])
    wall_tint = _tint(rng, 0.2, (0.85, 0.85, 0.82) if rng.uniform() < 0.5 else (0.75, 0.8, 0.85))
    if wall_base is not None:
        wall_tint = wall_base
    B.add((0, far_wall + 0.1, ceiling / 2), (80, 0.2, ceiling), "wall", SEM["wall"], tint=wall_tint)

    # lights along the corridors of the occupancy map, plus ambient
    cam_corr_y = -depth / 2 - corridor / 2
    corr_ys, corridors = [cam_corr_y], [corridor]
    for a, b in zip(range(2, len(rows_y), 2), range(1, len(rows_y), 2)):
        lo, hi = rows_y[b] + depths[b] / 2, rows_y[a] - depths[a] / 2
        corr_ys.append((lo + hi) / 2)
        corridors.append(hi - lo)
    spacing = _u(rng, r.light_spacing)
    warm = _u(rng, r.light_warmth)
    lcolor = (1.0 + 0.25 * warm, 1.0 + 0.05 * warm, 1.0 - 0.3 * warm)
    intensity = _u(rng, r.light_intensity)
    phase = float(rng.uniform(0, spacing))
    lights = []
    for cy in corr_ys:
        for k in range(-3, 4):
            lx = k * spacing + phase - spacing / 2
            lights.append(Light((lx, cy, ceiling - 0.4), lcolor, intensity * float(rng.uniform(0.85, 1.15))))
            B.add((lx, cy, ceiling - 0.3), (1.2, 0.25, 0.08), "lamp", SEM["wall"], tint=(1, 1, 1))
    # main light = the camera-corridor light closest to the rack centre (casts the shadows)
    main = int(np.argmin([abs(l.position[0]) + 100 * abs(l.position[1] - cam_corr_y) for l in lights]))
    if r.domain == "proxy-real":
        # a low, strong side light (like a loading-dock door) replaces the ceiling light as key light
        side = 1 if rng.uniform() < 0.5 else -1
        lights.insert(0, Light((side * float(rng.uniform(4, 8)), cam_corr_y - float(rng.uniform(0, 2)), float(rng.uniform(2.5, 4.5))),
                               (1.15, 1.0, 0.8), intensity * 1.6))
        main = 0
    lights = [lights[main]] + [l for i, l in enumerate(lights) if i != main]
    lights = lights[:1] + sorted(lights[1:], key=lambda l: l.position[0] ** 2 + (l.position[1] - cam_corr_y) ** 2)[:3]
    ambient = _u(rng, r.ambient)

    # clutter in corridors (never between the camera and the considered rack)
    n_clutter = _ui(rng, r.clutter)
    for _ in range(n_clutter):
        kind = rng.choice(["pallet", "forklift", "extinguisher"], p=[0.5, 0.2, 0.3])
        # clearance from the rack fronts: half the item's extent across the corridor + 10 cm
        clear = {"pallet": 0.55, "forklift": 0.65, "extinguisher": 0.2}[kind]
        along = {"pallet": 0.7, "forklift": 2.2, "extinguisher": 0.15}[kind]  # half length along x
        if background == "busy" and len(corr_ys) > 1 and rng.uniform() < 0.6:
            k = int(rng.integers(1, len(corr_ys)))
            half = corridors[k] / 2 - clear
            cy = corr_ys[k] + float(rng.uniform(-half, half)) * 0.8
            cx = float(rng.uniform(-8, 8))
        else:
            side = 1 if rng.uniform() < 0.5 else -1
            cx = side * (length / 2 + r.upright_width + along + float(rng.uniform(0.0, 3.5)))
            cy = -depth / 2 - clear - float(rng.uniform(0.0, max(0.05, corridor - 2 * clear)))
        if kind == "extinguisher":
            # stands next to an upright of the considered row
            hh = float(rng.uniform(0.45, 0.6))
            B.add((cx, cy, hh / 2), (0.17, 0.17, hh), "paint", SEM["clutter"], tint=(0.8, 0.06, 0.05), shape="cylinder")
            B.add((cx, cy, hh + 0.04), (0.06, 0.06, 0.08), "paint", SEM["clutter"], tint=(0.1, 0.1, 0.1), shape="cylinder")
        elif kind == "pallet":
            yaw = float(rng.uniform(-0.15, 0.15))  # long side along the corridor
            B.add((cx, cy, 0.072), (1.2, 0.8, 0.144), "pallet", SEM["clutter"], yaw=yaw)
            if rng.uniform() < 0.6:
                cat = _pick(rng, CARTONS)
                sz = float(rng.uniform(0.3, 1.2))
                B.add((cx, cy, 0.144 + sz / 2), (1.1, 0.7, sz), CATEGORY_NAMES[cat], SEM["box"], yaw=yaw, category=cat)
        else:
            yaw = (1 if rng.uniform() < 0.5 else -1) * math.pi / 2 + float(rng.uniform(-0.1, 0.1))  # along the corridor
            col = _tint(rng, 0.1, (0.95, 0.7, 0.05) if rng.uniform() < 0.6 else (0.9, 0.3, 0.1))
            c, s = math.cos(yaw), math.sin(yaw)
            B.add((cx, cy, 0.65), (1.0, 2.0, 1.0), "paint", SEM["clutter"], yaw=yaw, tint=col)
            B.add((cx, cy, 0.075), (1.05, 1.5, 0.15), "paint", SEM["clutter"], yaw=yaw, tint=(0.06, 0.06, 0.06))
            mx, my = cx - s * 1.05, cy + c * 1.05  # mast at the front end of the body
            for off in (-0.35, 0.35):
                B.add((mx + c * off, my + s * off, 1.15), (0.09, 0.09, 2.1), "steel", SEM["clutter"], yaw=yaw, tint=(0.2, 0.2, 0.2))
            B.add((mx - s * 0.5, my + c * 0.5, 0.08), (0.8, 1.0, 0.06), "steel", SEM["clutter"], yaw=yaw, tint=(0.15, 0.15, 0.15))
            B.add((cx, cy, 2.15), (1.0, 1.2, 0.06), "paint", SEM["clutter"], yaw=yaw, tint=(0.1, 0.1, 0.1))

    cam, visible = _sample_camera(rng, r, length, depth, shelves, corridor if background == "busy" else None,
                                  max_camera_tries, tall_rack)
    effects = _sample_effects(rng, r)
    # a wide lens gets at most the barrel distortion that keeps its corners (effects.k1_limit)
    effects["distortion_k1"] = max(effects["distortion_k1"], k1_limit(cam.K, cam.width, cam.height))
    cam.k1 = effects["distortion_k1"]
    window = heights = layout_row = None
    if r.layout_extent in ("frame", "row"):
        lo = shelves[visible[0]].board_top
        hi = shelves[visible[-1]].board_top + shelves[visible[-1]].clear_height
        if row_boxes is None:
            window = frame_window(cam, length, depth, (lo + hi) / 2)
        else:   # the row's front as far as the image shows it, at most the grid's extent
            layout_row = (run[0] * pitch_x - length / 2, run[1] * pitch_x + length / 2)
            samples = max(801, round((layout_row[1] - layout_row[0]) / length * 800) + 1)   # a bay's sampling step
            shown = shown_part(cam, *layout_row, depth, (lo + hi) / 2, samples)
            # the image's columns miss the row's front: the considered bay
            window = (-length / 2, length / 2) if shown is None else _clip_window(shown, r.extent_m)
        x = 0.0 if window is None else (window[0] + window[1]) / 2
        heights = [frame_height(cam, x, depth, shelves[k].board_top, shelves[k].clear_height) for k in visible]
        heights = heights if any(h is not None for h in heights) else None
    occ_rows = ["".join("#" if v else "." for v in row) for row in occ]
    occlusion = _u(rng, r.ambient_occlusion)   # drawn last: recipes without it keep every other draw
    return Scene(index=index, seed=seed, recipe=r.name, objects=B.objects, shelves=shelves, rack_length=length,
                 rack_depth=depth, visible=visible, camera=cam, lights=lights, ambient=ambient,
                 ambient_color=(1.0, 1.0, 1.0), main_light=0, background=background, occupancy=occ_rows,
                 effects=effects, domain=r.domain, shadows=r.shadows, occlusion=occlusion, rack_style=style, layout_window=window,
                 layout_heights=heights, layout_row=layout_row, row_boxes=row_boxes)


#: a world point counts as seen only this far (metres, along the optical axis) in front of the camera
IN_FRONT_M = 0.05


def _in_image(cam: Camera, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether the image's columns and rows show world points (N, 3), lens distortion included
    (where its model holds: `Camera.lens_holds`), at least `IN_FRONT_M` in front of the camera."""
    uv, zc = cam.project_z(pts)
    ok = (zc > IN_FRONT_M) & cam.lens_holds(uv)
    uv = distort_points(cam.K, cam.k1, uv)
    return ok & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width), ok & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)


def shown_part(cam: Camera, a: float, b: float, depth: float, z: float, samples: int) -> tuple | None:
    """(x0, x1): the part of a rack front's edge at height z (world x from a to b, y = -depth/2)
    that the image's columns show, sampled at `samples` points; (a, b) when they show all of it,
    None when none."""
    xs = np.linspace(a, b, samples)
    seen = _in_image(cam, np.c_[xs, np.full_like(xs, -depth / 2), np.full_like(xs, z)])[0]
    if not seen.any():
        return None
    step = (b - a) / (samples - 1)
    x = xs[seen]
    # each end half a sample beyond the last point seen (the true edge lies within it)
    return (max(float(x[0]) - step / 2, a), min(float(x[-1]) + step / 2, b))


def frame_window(cam: Camera, length: float, depth: float, z: float, samples: int = 801) -> tuple | None:
    """(x0, x1): the part of the rack's front edge at height z (world x from -length/2 to
    length/2, y = -depth/2) that the image's columns show, sampled every length / (samples - 1);
    None when they show all of it (or none: the whole bay is kept)."""
    part = shown_part(cam, -length / 2, length / 2, depth, z, samples)
    return None if part is None or part == (-length / 2, length / 2) else part


def _clip_window(window: tuple, extent: float) -> tuple:
    """At most `extent` metres of a window, as close to centred on the considered bay (x = 0)
    as the window allows (the layout grid's span)."""
    x0, x1 = window
    if x1 - x0 <= extent:
        return window
    c = min(max(0.0, x0 + extent / 2), x1 - extent / 2)
    return (c - extent / 2, c + extent / 2)


def frame_height(cam: Camera, x: float, depth: float, board: float, clear: float,
                 samples: int = 401) -> float | None:
    """How much of a level's opening (from its board top, `clear` metres up) the image shows
    above its board on the rack's front plane at x, when the frame's top edge cuts it; None when
    the image shows it up to the top (or shows none of it)."""
    zs = board + np.linspace(0.0, clear, samples)
    cols, rows = _in_image(cam, np.c_[np.full_like(zs, x), np.full_like(zs, -depth / 2), zs])
    seen = cols & rows
    if seen[-1] or not seen.any():
        return None
    top = int(np.nonzero(seen)[0].max())
    return min(float(zs[top] - board) + clear / (samples - 1) / 2, clear)


def rotation_world_to_cam(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """World -> camera rotation of a camera looking along +y (world) with the given jitter
    (radians): yaw about world z, then pitch about the camera x axis (positive = look up),
    then roll about the optical axis."""
    R0 = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # camera axes in world: rows x_c, y_c, z_c
    cz, sz = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1.0]])
    cp, sp = math.cos(pitch), math.sin(pitch)
    Rx = np.array([[1.0, 0, 0], [0, cp, sp], [0, -sp, cp]])
    cr, sr = math.cos(roll), math.sin(roll)
    Rr = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1.0]])
    # camera -> world = Rz @ R0^T @ Rx^T-ish; compose in camera frame and invert
    R_cw = Rz @ R0.T @ Rx.T @ Rr.T
    return R_cw.T


def visible_shelves(cam: Camera, length: float, depth: float, shelves: list, fraction: float,
                    max_range: float, board_fraction: float = 1.0) -> list[int]:
    """The visible-shelf rule (documented in docs/waresynth.md). Shelf i is visible when the
    vertical segment of its front opening at the x of the camera (clamped to the rack), from
    the board top to board top + clear height on the rack's front plane, projects in front of
    the camera with at least `fraction` of its image-height inside the image rows, its column
    inside the image, and its midpoint within `max_range` metres of the camera. A shelf whose
    board (the segment's lower end) is inside the image rows needs only `board_fraction` of it
    (below `fraction`: a level whose top the frame cuts counts, as a labeller counts it)."""
    C = cam.center
    x = float(np.clip(C[0], -length / 2, length / 2))
    out = []
    for i, sh in enumerate(shelves):
        pts = np.array([[x, -depth / 2, sh.board_top], [x, -depth / 2, sh.board_top + sh.clear_height]])
        uv, zc = cam.project_z(pts)
        if (zc <= 0.05).any():
            continue
        mid = pts.mean(axis=0)
        if np.linalg.norm(mid - C) > max_range:
            continue
        v0, v1 = sorted(uv[:, 1])
        span = v1 - v0
        inside = max(0.0, min(v1, cam.height) - max(v0, 0.0))
        col = uv[:, 0].mean()
        need = fraction
        if 0 <= uv[0, 1] < cam.height:   # the board's front edge is in the image
            need = min(fraction, board_fraction)
        if span > 0 and inside >= need * span and 0 <= col < cam.width:
            out.append(i)
    return out


def _sample_camera(rng, r: Recipe, length, depth, shelves, corridor, tries, tall_rack=None):
    W, H = r.image_width, r.image_height
    n = len(shelves)
    last = None
    for _ in range(tries):
        # the extra draw only where zoom is on: recipes without it keep their random streams
        f = _u(rng, r.long_focal_px if r.long_lens_fraction and rng.random() < r.long_lens_fraction else r.focal_px)
        # likewise the tall view's draw: frame more levels than R, label the lowest R of those visible
        if tall_rack is None:
            tall = n > r.R and bool(r.tall_view_fraction) and rng.random() < r.tall_view_fraction
        else:                               # decided with the rack (sample_scene, tall_view_shelves)
            tall = tall_rack and n > r.R
        k = int(rng.integers(r.R + 1, n + 1)) if tall else int(rng.integers(1, min(r.R, n) + 1))
        s = int(rng.integers(0, n - k + 1))
        lo = shelves[s].board_top
        hi = shelves[s + k - 1].board_top + shelves[s + k - 1].clear_height
        band = hi - lo
        dist = f * band / H * float(rng.uniform(*r.framing))
        dmax = r.camera_distance[1] if corridor is None else min(r.camera_distance[1], corridor - 0.3)
        dist = float(np.clip(dist, r.camera_distance[0], max(dmax, r.camera_distance[0])))
        cz = float(np.clip((lo + hi) / 2 + rng.uniform(-0.1, 0.1) * band, *r.camera_height))
        cx = float(rng.uniform(-r.camera_x, r.camera_x)) * length
        C = np.array([cx, -depth / 2 - dist, cz])
        yaw = math.radians(float(rng.uniform(-r.yaw_jitter_deg, r.yaw_jitter_deg)))
        pitch = math.radians(float(rng.uniform(-r.pitch_jitter_deg, r.pitch_jitter_deg)))
        roll = math.radians(float(rng.uniform(-r.roll_jitter_deg, r.roll_jitter_deg)))
        R = rotation_world_to_cam(yaw, pitch, roll)
        K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
        cam = Camera(K=K, R=R, t=-R @ C, width=W, height=H)
        vis = visible_shelves(cam, length, depth, shelves, r.visible_fraction, r.detection_range_m,
                              r.visible_fraction_board)
        last = (cam, vis)
        if 1 <= len(vis) <= r.R or (tall and len(vis) > r.R):
            return cam, vis[:r.R]
    raise ValueError(f"recipe {r.name}: no camera placement with 1..{r.R} visible shelves in {tries} tries "
                     f"(check camera_distance / camera_height / focal_px against the rack size); last try saw "
                     f"{len(last[1])} shelves")


def _sample_effects(rng, r: Recipe) -> dict:
    wb = r.white_balance
    return {
        "exposure": _u(rng, r.exposure),
        "white_balance": [float(1 + rng.uniform(-wb, wb)) for _ in range(3)] if wb > 0 else [1.0, 1.0, 1.0],
        "blur_sigma": _u(rng, r.blur_sigma),
        "noise_std": _u(rng, r.noise_std),
        "vignetting": _u(rng, r.vignetting),
        "jpeg_quality": _ui(rng, r.jpeg_quality),
        "distortion_k1": _u(rng, r.distortion_k1),
        "noise_seed": int(rng.integers(0, 2**31 - 1)),
    }
