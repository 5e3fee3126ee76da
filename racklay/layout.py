"""The layout convention: one home for grids, classes, pixel encoding and rasterising.

Everything that turns shelves and boxes into layout pixels, or layout pixels back into metres,
calls this module: the WareSynth generator, the annotation tool, the model's data pipeline, the
metrics and the 3D rack reasoning. If you find yourself writing metre/pixel arithmetic anywhere
else, add it here instead.

Convention (see docs/architecture.md for a figure)
--------------------------------------------------
Classes (model space):   BACKGROUND = 0, SHELF = 1 (free shelf space), BOX = 2 (occupied).
File encoding (RackLay): 0 / 115 / 255, uint8. Decoding is strict: any other value is an error.

Grid: a layout is D x D pixels covering L x L metres (defaults D = 512, L = 8 m, so
1.5625 cm/pixel). R channels (default 4), one per shelf, channel 0 = lowest *visible* shelf;
channels of shelves that are not visible are all background; an image showing more than R
levels has the lowest R visible ones as its channels.

Shelf-centric frame, per shelf i: origin at the centre of the shelf board's top surface;
x along the rack's length (to the camera's right), y along its depth (away from the camera),
z up.

What is a shelf, what is a box (pallet racking included):
- A shelf is every level that stores goods: a board, a wire deck, or a pair of beams with
  nothing between them (the level's rectangle is then the bay between the beams, its "board
  top" the beams' top). The floor under a rack's first beam, where loads stand on the floor, is
  a shelf too: the lowest channel, its board top the floor (z = 0 in the world), its clear
  height up to the first beam's top. WareSynth (`floor_level`) and the annotator agree on this.
- A box is one load unit: a carton, crate or stack of them on a shelf, or a pallet with
  everything on it (cartons, a stretch-wrapped load, crates), from the pallet's underside on the
  beams to the load's top; one load standing on two pallets (a long crate, board stack or
  appliance carton) is one box across both. The pallet is never a box of its own and never part
  of the shelf.

How much of a bay: a labelled photo draws the bay as far as the photo shows it (where the
frame's left or right edge cuts the bay, the shelf ends there; where its top edge cuts a level,
the level's opening and its boxes end there: docs/annotate.md). WareSynth draws the same with
`layout_extent: frame` (`rasterize_shelf(window=...)`, the scene's `layout_heights`), and with
`row` continues a level across shared uprights into the neighbouring bays as far as the image
shows them, as a labeller draws "the bay (or bays)" a photo shows; with `bay`, the paper's
convention and `complex`'s, it draws the whole bay however much is in view.

Rack plane (the annotation tool's, annotate.geometry): u along the rack's front face from its
left edge (0 .. W), v up from its bottom. A shelf spans the rack's width, so x = u - W/2 and
u = x + W/2 (`u_to_x`, `x_to_u`: the one place this shift is written). Depth is measured the same
way from the board's front edge: y = offset - depth/2 (`offset_to_y`, `y_to_offset`).

Top view T_i: column c <-> x, row r <-> y. Column centres are x = (c + 0.5 - D/2) * res, so x
grows to the right and x = 0 is the centre line of the map. Rows run the other way: the far side
(back of the shelf, +y) is at the top of the map, y = (D/2 - r - 0.5) * res. The shelf rectangle
is centred in the map.

Front view F_i: the same columns as T_i (both views share the x axis), rows <-> z with up being
up: z = (D/2 - r - 0.5) * res. The board's top surface (z = 0) lies on the centre row boundary,
so the shelf's free space (length x clear height) fills rows D/2 - 1 upward.

A pixel belongs to a shape when its *centre* lies inside the shape (half-open on the low side
of each axis in metric coordinates: lo <= v < hi), which makes adjacent shapes tile without
gaps or overlaps and makes pixel counts exact.

Flip: a horizontal flip of the image (mirror left-right) corresponds to a left-right flip of
every T_i and F_i (x -> -x; reverse the columns). Rows are unchanged. `hflip_layouts` does it.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Iterable, NamedTuple, Sequence

import numpy as np

BACKGROUND, SHELF, BOX = 0, 1, 2
CLASS_NAMES = ("background", "shelf", "box")
NUM_CLASSES = 3
#: uint8 value written in RackLay .npy files for each class id
FILE_VALUES = np.array([0, 115, 255], dtype=np.uint8)
DEFAULT_D = 512
DEFAULT_EXTENT_M = 8.0
DEFAULT_R = 4
#: WareSynth drew the front-view free space 5 cm taller than the inter-shelf height.
FRONT_CLEARANCE_PAD_M = 0.05
VIEWS = ("top", "front")


class LayoutError(ValueError):
    """A layout array that breaks the convention (bad values, shape or dtype)."""


@dataclass(frozen=True)
class Grid:
    """A D x D metric grid of `extent` metres a side, centred on the shelf origin."""

    size: int = DEFAULT_D
    extent: float = DEFAULT_EXTENT_M

    def __post_init__(self):
        if int(self.size) != self.size or self.size <= 0 or self.size % 2:
            raise ValueError(f"grid size must be a positive even integer, got {self.size}")
        if not self.extent > 0:
            raise ValueError(f"grid extent must be positive metres, got {self.extent}")

    @property
    def res(self) -> float:
        """Metres per pixel."""
        return self.extent / self.size

    # --- metres <-> pixels. Pixel coordinates are continuous: pixel c spans [c, c + 1). ---
    def x_to_col(self, x):
        """Metric x (shelf frame) -> continuous column coordinate."""
        return np.asarray(x, dtype=np.float64) / self.res + self.size / 2

    def col_to_x(self, col):
        """Continuous column coordinate -> metric x. col_to_x(c + 0.5) is pixel c's centre."""
        return (np.asarray(col, dtype=np.float64) - self.size / 2) * self.res

    def y_to_row(self, y):
        """Metric y (depth, away from camera) -> continuous top-view row (far side on top)."""
        return self.size / 2 - np.asarray(y, dtype=np.float64) / self.res

    def row_to_y(self, row):
        return (self.size / 2 - np.asarray(row, dtype=np.float64)) * self.res

    # z (up) uses the same mapping in the front view as y does in the top view.
    z_to_row = y_to_row
    row_to_z = row_to_y

    def centers(self) -> np.ndarray:
        """Metric coordinate of every column centre (equal to row centres' y/z reversed)."""
        return self.col_to_x(np.arange(self.size) + 0.5)

    def row_centers(self) -> np.ndarray:
        """Metric y (top view) or z (front view) of every row centre, top row first."""
        return self.row_to_y(np.arange(self.size) + 0.5)

    def pixel_area_m2(self) -> float:
        return self.res * self.res

    # --- pixel spans <-> metric spans (used to read shapes back out of layouts) ---
    def col_span_to_x(self, c0: int, c1: int) -> tuple[float, float]:
        """Metric x-range [x0, x1) covered by the pixel columns c0 .. c1 - 1 (pixel edges)."""
        return float(self.col_to_x(c0)), float(self.col_to_x(c1))

    def row_span_to_v(self, r0: int, r1: int) -> tuple[float, float]:
        """Metric (lo, hi) range of y (top view) or z (front view) covered by the pixel rows
        r0 .. r1 - 1. Rows grow downward, so lo comes from r1 and hi from r0."""
        return float(self.row_to_y(r1)), float(self.row_to_y(r0))

    def px_to_m(self, n_pixels):
        """A length of `n_pixels` pixels in metres."""
        return np.asarray(n_pixels, dtype=np.float64) * self.res

    def m_to_px(self, metres) -> int:
        """A metric length as a whole number of pixels (rounded, at least 1)."""
        return max(1, int(round(float(metres) / self.res)))


def u_to_x(u, width: float):
    """Rack-plane u (metres from the rack's left edge, 0 .. width) -> shelf-frame x (metres from
    the shelf's centre line): x = u - width/2. Scalars or numpy arrays."""
    return u - width / 2


def x_to_u(x, width: float):
    """Shelf-frame x -> rack-plane u: u = x + width/2 (the inverse of u_to_x)."""
    return x + width / 2


def offset_to_y(offset, depth: float):
    """Distance behind the board's front edge (0 .. depth, the annotation tool's box `front_offset`)
    -> shelf-frame y (metres from the board's centre line, +y away from the camera):
    y = offset - depth/2. Scalars or numpy arrays."""
    return offset - depth / 2


def y_to_offset(y, depth: float):
    """Shelf-frame y -> distance behind the board's front edge (the inverse of offset_to_y)."""
    return y + depth / 2


def _span_mask(centres: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return (centres >= lo) & (centres < hi)


def fill_axis_rect(canvas: np.ndarray, grid: Grid, x0: float, x1: float, v0: float, v1: float,
                   value: int) -> np.ndarray:
    """Fill pixels whose centre has x in [x0, x1) and y/z in [v0, v1) with `value`, in place.

    Works for both views: v is y in the top view and z in the front view.
    """
    xs = _span_mask(grid.centers(), min(x0, x1), max(x0, x1))
    vs = _span_mask(grid.row_centers(), min(v0, v1), max(v0, v1))
    canvas[np.ix_(vs, xs)] = value
    return canvas


def oriented_rect_mask(grid: Grid, cx: float, cy: float, sx: float, sy: float,
                       yaw: float) -> np.ndarray:
    """Boolean D x D top-view mask of a rectangle of size (sx, sy) centred at (cx, cy), rotated
    by `yaw` radians counter-clockwise about z (seen from above). Vectorised over the shape's
    bounding box only."""
    D = grid.size
    mask = np.zeros((D, D), dtype=bool)
    c, s = np.cos(yaw), np.sin(yaw)
    hx, hy = abs(sx) / 2, abs(sy) / 2
    ex = abs(c) * hx + abs(s) * hy  # half-extent of the rotated rectangle's bounding box
    ey = abs(s) * hx + abs(c) * hy
    c0 = max(int(np.floor(grid.x_to_col(cx - ex))) - 1, 0)
    c1 = min(int(np.ceil(grid.x_to_col(cx + ex))) + 1, D)
    r0 = max(int(np.floor(grid.y_to_row(cy + ey))) - 1, 0)
    r1 = min(int(np.ceil(grid.y_to_row(cy - ey))) + 1, D)
    if c0 >= c1 or r0 >= r1:
        return mask
    px = grid.col_to_x(np.arange(c0, c1) + 0.5)[None, :] - cx
    py = grid.row_to_y(np.arange(r0, r1) + 0.5)[:, None] - cy
    u = c * px + s * py  # coordinates in the box's own frame
    v = -s * px + c * py
    mask[r0:r1, c0:c1] = (u >= -hx) & (u < hx) & (v >= -hy) & (v < hy)
    return mask


@dataclass(frozen=True)
class Shelf:
    """One shelf in its own frame: board `length` along x, `depth` along y, free space of
    `clear_height` above the board top (the inter-shelf distance for all but the top shelf)."""

    length: float
    depth: float
    clear_height: float

    def __post_init__(self):
        for name in ("length", "depth", "clear_height"):
            if not getattr(self, name) > 0:
                raise ValueError(f"shelf {name} must be positive metres, got {getattr(self, name)}")


def half_extents(sx: float, sy: float, yaw: float) -> tuple[float, float]:
    """Half extents along x and y of an sx x sy footprint rotated by `yaw` radians (its
    axis-aligned bounding box, as `Box.x_range` / `y_range` see it)."""
    c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
    return c * sx / 2 + s * sy / 2, s * sx / 2 + c * sy / 2


@dataclass(frozen=True)
class Box:
    """A box (or box stack) standing on a shelf, in the shelf frame: footprint centre (cx, cy),
    size (sx along its own x, sy along its own y, sz up), bottom at height z0 above the board,
    rotated by `yaw` radians about z."""

    cx: float
    cy: float
    sx: float
    sy: float
    sz: float
    z0: float = 0.0
    yaw: float = 0.0

    def x_range(self) -> tuple[float, float]:
        """Extent of the rotated footprint along x (what the front view sees)."""
        ex, _ = half_extents(self.sx, self.sy, self.yaw)
        return self.cx - ex, self.cx + ex

    def y_range(self) -> tuple[float, float]:
        _, ey = half_extents(self.sx, self.sy, self.yaw)
        return self.cy - ey, self.cy + ey

    def corners_xy(self) -> np.ndarray:
        """4 x 2 footprint corners in the shelf frame, counter-clockwise."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * [self.sx / 2, self.sy / 2]
        rot = np.array([[c, -s], [s, c]])
        return local @ rot.T + [self.cx, self.cy]


@dataclass
class ShelfLayout:
    """Class-id top and front layouts (D x D uint8 each) of one shelf."""

    top: np.ndarray
    front: np.ndarray


def rasterize_shelf(shelf: Shelf, boxes: Iterable[Box], grid: Grid = Grid(),
                    front_pad: float = FRONT_CLEARANCE_PAD_M,
                    window: tuple[float, float] | None = None) -> ShelfLayout:
    """Draw one shelf and its boxes into class-id top and front layouts.

    Top view: the shelf rectangle (length x depth, centred) as SHELF, each box's rotated
    footprint as BOX on top. Front view: the free space (length x (clear_height + front_pad))
    from the board upward as SHELF, each box's elevation (x-range of its rotated footprint x
    [z0, z0 + sz]) as BOX. Boxes behind each other merge in the front view, stacked boxes merge
    in the top view, as in WareSynth.

    window=(x0, x1): only the part of the shelf with x0 <= x < x1 (shelf frame) is drawn, moved
    so that the part is centred: the shelf as far as a photo shows it, a shelf of length x1 - x0
    whose boxes the window's ends cut (the labelling guide's rule for a bay the frame cuts,
    docs/annotate.md). The window is clipped to the shelf.
    """
    if window is not None:
        x0, x1 = max(float(window[0]), -shelf.length / 2), min(float(window[1]), shelf.length / 2)
        if not x1 > x0:
            raise ValueError(f"window {window} does not overlap the shelf (length {shelf.length} m)")
        c, half = (x0 + x1) / 2, (x1 - x0) / 2
        part = rasterize_shelf(Shelf(x1 - x0, shelf.depth, shelf.clear_height),
                               [replace(b, cx=b.cx - c) for b in boxes], grid, front_pad)
        outside = ~_span_mask(grid.centers(), -half, half)
        part.top[:, outside] = BACKGROUND
        part.front[:, outside] = BACKGROUND
        return part
    D = grid.size
    top = np.zeros((D, D), dtype=np.uint8)
    front = np.zeros((D, D), dtype=np.uint8)
    L, W = shelf.length, shelf.depth
    fill_axis_rect(top, grid, -L / 2, L / 2, -W / 2, W / 2, SHELF)
    fill_axis_rect(front, grid, -L / 2, L / 2, 0.0, shelf.clear_height + front_pad, SHELF)
    for b in boxes:
        top[oriented_rect_mask(grid, b.cx, b.cy, b.sx, b.sy, b.yaw)] = BOX
        x0, x1 = b.x_range()
        fill_axis_rect(front, grid, x0, x1, b.z0, b.z0 + b.sz, BOX)
    return ShelfLayout(top, front)


def stack_shelves(layouts: Sequence[ShelfLayout | None], R: int = DEFAULT_R,
                  grid: Grid = Grid()) -> tuple[np.ndarray, np.ndarray]:
    """Stack per-shelf layouts (lowest visible shelf first) into R x D x D class-id arrays.
    Missing shelves (fewer than R, or None entries) are all background."""
    if len(layouts) > R:
        raise LayoutError(f"{len(layouts)} shelves given but only R={R} channels")
    D = grid.size
    top = np.zeros((R, D, D), dtype=np.uint8)
    front = np.zeros((R, D, D), dtype=np.uint8)
    for i, lay in enumerate(layouts):
        if lay is not None:
            top[i], front[i] = lay.top, lay.front
    return top, front


# --- encoding ------------------------------------------------------------------------------
_VALUE_TO_CLASS = np.full(256, 255, dtype=np.uint8)
_VALUE_TO_CLASS[FILE_VALUES] = np.arange(NUM_CLASSES, dtype=np.uint8)


def encode(classes: np.ndarray) -> np.ndarray:
    """Class ids {0, 1, 2} -> file values {0, 115, 255} (uint8). Strict."""
    classes = np.asarray(classes)
    if classes.size and (classes.min() < 0 or classes.max() >= NUM_CLASSES):
        bad = np.setdiff1d(np.unique(classes), np.arange(NUM_CLASSES))
        raise LayoutError(f"class ids must be 0, 1 or 2; found {bad[:5].tolist()}")
    if classes.dtype == np.uint8:   # (background's value is 0) ~10x faster than a look-up with intp indices
        out = np.multiply(classes, FILE_VALUES[SHELF])
        out[classes == BOX] = FILE_VALUES[BOX]
        return out
    return FILE_VALUES[classes.astype(np.intp)]


def decode(values: np.ndarray, source: str = "layout") -> np.ndarray:
    """File values {0, 115, 255} -> class ids {0, 1, 2}. Any other value raises LayoutError
    naming the value and `source`."""
    values = np.asarray(values)
    if values.dtype != np.uint8:
        if not np.issubdtype(values.dtype, np.integer):
            raise LayoutError(f"{source}: dtype {values.dtype}, expected uint8 values 0/115/255")
        if values.size and (values.min() < 0 or values.max() > 255):
            raise LayoutError(f"{source}: values outside 0..255 (expected 0/115/255)")
        values = values.astype(np.uint8)
    out = _VALUE_TO_CLASS[values]
    if values.size and out.max() == 255:
        bad = np.unique(values[out == 255])
        raise LayoutError(f"{source}: stray value(s) {bad[:5].tolist()} (allowed: 0, 115, 255)")
    return out


def check_stack(arr: np.ndarray, R: int | None = None, D: int | None = None,
                source: str = "layout", encoded: bool = True) -> None:
    """Raise LayoutError unless `arr` is an R x D x D layout stack of allowed values."""
    if arr.ndim != 3 or arr.shape[1] != arr.shape[2]:
        raise LayoutError(f"{source}: shape {tuple(arr.shape)}, expected (R, D, D)")
    if R is not None and arr.shape[0] != R:
        raise LayoutError(f"{source}: {arr.shape[0]} shelf channels, expected R={R}")
    if D is not None and arr.shape[1] != D:
        raise LayoutError(f"{source}: {arr.shape[1]}x{arr.shape[2]} layout, expected D={D}")
    if encoded:
        if arr.dtype != np.uint8:
            raise LayoutError(f"{source}: dtype {arr.dtype}, expected uint8")
        decode(arr, source)
    elif arr.size and arr.max() >= NUM_CLASSES:
        raise LayoutError(f"{source}: class ids must be 0, 1 or 2")


def hflip_layouts(layouts: np.ndarray) -> np.ndarray:
    """Layouts matching a horizontally flipped image: reverse the columns (x -> -x) of every
    channel. Works on (..., D, D) arrays."""
    return np.ascontiguousarray(np.asarray(layouts)[..., ::-1])


def visible_shelf_count(layouts: np.ndarray) -> int:
    """Number of leading channels that contain any non-background pixel."""
    flat = np.asarray(layouts).reshape(layouts.shape[0], -1)
    return int((flat.max(axis=1) > 0).sum())


def resize_layouts(layouts: np.ndarray, size: int) -> np.ndarray:
    """Nearest-neighbour resize of (..., D, D) layouts to (..., size, size), sampling at pixel
    centres so the metric convention is preserved (the grid extent stays the same)."""
    D = layouts.shape[-1]
    if size == D:
        return layouts
    idx = np.minimum(((np.arange(size) + 0.5) * D / size).astype(np.intp), D - 1)
    return layouts[..., idx[:, None], idx[None, :]]


def layout_area_m2(mask: np.ndarray, grid: Grid) -> float:
    """Metric area of a boolean layout mask."""
    return float(np.count_nonzero(mask)) * grid.pixel_area_m2()


def box_runs(layouts: np.ndarray) -> np.ndarray:
    """(..., D, D) class-id layouts -> (...,) the number of separate runs of box columns along x
    (boxes with a gap between them count as two; touching boxes are one run, as the layout cannot
    tell them apart)."""
    cols = (np.asarray(layouts) == BOX).any(axis=-2).astype(np.int8)
    pad = np.zeros(cols.shape[:-1] + (1,), np.int8)
    return (np.diff(np.concatenate([pad, cols, pad], -1), axis=-1) > 0).sum(-1)


#: a predicted gap between boxes is the truth's when the two lie within this fraction of their
#: shelf's length of each other (5 %: 15 cm of a 3 m beam, about one pallet gap), each measured along
#: its own shelf, so a prediction of the wrong metric size is not penalised twice
GAP_TOLERANCE = 0.05


class Separation(NamedTuple):
    """Per shelf channel: the truth has >= 2 box runs; the prediction has; both on that channel;
    both, with the prediction's gaps where the truth's are (`gaps_match`)."""
    truth: np.ndarray
    pred: np.ndarray
    hit: np.ndarray
    placed: np.ndarray


def box_gaps(layout: np.ndarray) -> list[tuple[float, float]]:
    """The gaps between box runs of one (D, D) class-id layout, as (start, end) fractions of its
    shelf's length along x (the shelf: the longest run of shelf-or-box columns, `shelf_lengths`)."""
    cols = np.asarray(layout) > BACKGROUND
    fg, box = cols.any(axis=-2), (np.asarray(layout) == BOX).any(axis=-2)
    if not box.any():
        return []
    edges = np.diff(np.concatenate([[0], fg.astype(np.int8), [0]]))
    starts, ends = np.nonzero(edges > 0)[0], np.nonzero(edges < 0)[0]
    k = int(np.argmax(ends - starts))
    s0, n = starts[k], max(ends[k] - starts[k], 1)
    b = np.nonzero(box)[0]
    jumps = np.nonzero(np.diff(b) > 1)[0]            # a gap follows box column b[j]
    return [((b[j] + 1 - s0) / n, (b[j + 1] - s0) / n) for j in jumps]


def gaps_match(truth: list, pred: list, tol: float = GAP_TOLERANCE) -> bool:
    """Whether two lists of gaps (`box_gaps`) are the same loads' gaps: as many, and each predicted
    gap within `tol` (fraction of the shelf's length) of the true gap of the same rank."""
    return len(truth) == len(pred) and all(plo - tol <= thi and phi + tol >= tlo
                                           for (tlo, thi), (plo, phi) in zip(truth, pred))


def separated_shelves(truth: np.ndarray, pred: np.ndarray, tol: float = GAP_TOLERANCE) -> Separation:
    """The structured-model issue's "separate boxes where the photo shows separate boxes", per
    shelf, for (..., R, D, D) front-view class-id layouts (`Separation`). A separation on another
    channel than the truth's is not a hit (it is what a phantom shelf looks like); a hit is
    `placed` when the prediction's gaps are the truth's, each within `tol` of the shelf's length
    (`gaps_match`: a model unsure where the loads are cuts somewhere: a hit, rarely placed)."""
    truth, pred = np.asarray(truth), np.asarray(pred)
    t, p = box_runs(truth) >= 2, box_runs(pred) >= 2
    hit = t & p
    placed = np.zeros_like(hit)
    for i in zip(*np.nonzero(hit)):
        placed[i] = gaps_match(box_gaps(truth[i]), box_gaps(pred[i]), tol)
    return Separation(t, p, hit, placed)


def shelf_lengths(layouts: np.ndarray, grid: Grid) -> np.ndarray:
    """Metric length of each channel's shelf in (R, D, D) class-id layouts of either view: the
    longest run of adjacent columns holding a shelf or box pixel, times the pixel size (stray
    pixels beside the shelf do not count; 0 for an empty channel)."""
    cols = (np.asarray(layouts) > BACKGROUND).any(axis=-2)
    out = np.zeros(cols.shape[0])
    for i, c in enumerate(cols):
        if c.any():
            edges = np.diff(np.concatenate([[0], c.astype(np.int8), [0]]))
            out[i] = (np.nonzero(edges < 0)[0] - np.nonzero(edges > 0)[0]).max()
    return out * grid.res


def length_factors(views, grid: Grid, length) -> np.ndarray:
    """Per shelf channel, the factor that scales it to `length` metres (a number, or one per
    channel; NaN or 0 leaves that channel): one factor per shelf for both views, from its length
    measured as the longest of its views' (`shelf_lengths`; the views share the x axis). `views`:
    an iterable of (R, D, D) class-id layouts of the same shelves. Empty channels get 1."""
    have = np.max([shelf_lengths(v, grid) for v in views], axis=0)
    want = np.broadcast_to(np.asarray(length, dtype=np.float64), have.shape)
    ok = np.isfinite(want) & (want > 0) & (have > 0)
    return np.where(ok, want / np.where(have > 0, have, 1.0), 1.0)


def scale_about_origin(arrays: np.ndarray, factors, fill=None) -> np.ndarray:
    """Uniformly scale every channel of (R, ..., D, D) layouts (class ids, or per-class
    probabilities (R, 3, D, D)) about the shelf origin by factors[i] (a known dimension fixing the
    scale: the shape stays, the metric size changes). Both views are the same operation: columns
    about x = 0, rows about the centre row boundary (y = 0 in the top view, the board top z = 0 in
    the front view). Nearest neighbour at pixel centres; what comes from outside the grid is
    background (or `fill`, e.g. the one-hot background probability, broadcast over the pixels).
    Factors of 1 (or of empty channels, which stay empty) leave a channel unchanged."""
    a = np.asarray(arrays)
    D = a.shape[-1]
    out = np.empty_like(a)
    centre = (np.arange(D) + 0.5 - D / 2)
    for i, k in enumerate(np.broadcast_to(np.asarray(factors, dtype=np.float64), (a.shape[0],))):
        if not np.isfinite(k) or k <= 0:
            raise ValueError(f"scale factor for channel {i} must be a positive number, got {k}")
        src = np.floor(D / 2 + centre / k).astype(np.intp)          # column; rows use the mirrored map
        src_rows = D - 1 - src[::-1]
        ok_c, ok_r = (src >= 0) & (src < D), (src_rows >= 0) & (src_rows < D)
        ch = a[i][..., np.clip(src_rows, 0, D - 1)[:, None], np.clip(src, 0, D - 1)[None, :]]
        bad = ~(ok_r[:, None] & ok_c[None, :])
        if fill is None:
            ch[..., bad] = BACKGROUND
        else:
            ch[..., bad] = np.asarray(fill, dtype=a.dtype).reshape(-1, 1)
        out[i] = ch
    return out


def check_shelf_length(length, grid: Grid) -> None:
    """A known shelf length (metres; a number, or one per channel, NaN for none) must be one the
    grid can draw: at least two pixels and at most the grid's extent. Raises ValueError naming the
    range (a length typed in centimetres is the usual slip)."""
    want = np.asarray(length, dtype=np.float64)
    lo = 2 * grid.res
    bad = want[np.isfinite(want) & ((want < lo) | (want > grid.extent))]
    if bad.size or np.any(np.isinf(want)):
        raise ValueError(f"shelf length {length} m: outside what the {grid.extent:g} m, {grid.size}-pixel "
                         f"layout grid can draw ({lo:.3g} to {grid.extent:g} m; metres, not centimetres)")


def scale_shelves(layouts: dict, grid: Grid, length, probs: dict | None = None):
    """Every shelf of a prediction scaled to a known length: `layouts` {view: (R, D, D) class ids},
    `probs` {view: (R, 3, D, D)} (optional), `length` in metres (a number, or one per channel; NaN
    leaves a channel). One factor per shelf for both views and all its dimensions
    (`length_factors`), applied about the shelf origin (`scale_about_origin`; what comes from
    outside the grid is background). Returns (layouts, probs, factors)."""
    check_shelf_length(length, grid)
    views = [v for v in VIEWS if v in layouts]
    f = length_factors([layouts[v] for v in views], grid, length)
    bg = np.eye(NUM_CLASSES, dtype=np.float32)[BACKGROUND]
    out = {v: scale_about_origin(layouts[v], f) for v in views}
    out_p = {v: scale_about_origin(p, f, fill=bg) for v, p in (probs or {}).items()}
    return out, out_p, f


__all__ = [
    "BACKGROUND", "SHELF", "BOX", "CLASS_NAMES", "NUM_CLASSES", "FILE_VALUES", "DEFAULT_D",
    "DEFAULT_EXTENT_M", "DEFAULT_R", "FRONT_CLEARANCE_PAD_M", "VIEWS", "LayoutError", "Grid",
    "Shelf", "Box", "ShelfLayout", "fill_axis_rect", "oriented_rect_mask", "rasterize_shelf",
    "stack_shelves", "encode", "decode", "check_stack", "hflip_layouts",
    "visible_shelf_count", "resize_layouts", "layout_area_m2", "shelf_lengths", "length_factors",
    "scale_about_origin", "check_shelf_length", "scale_shelves",
]
