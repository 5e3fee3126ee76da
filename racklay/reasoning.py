"""Rack reasoning (paper §5.6): box-stack counts, metric free space and a 3D reconstruction
from each shelf's top-view T_i and front-view F_i class-id layouts.

Per shelf (one channel of the R x D x D stacks, predicted or ground truth):

1. Shelf extent. Top view: the largest connected region of shelf+box pixels gives the
   footprint (length along x x depth along y, from its bounding box over the rows/columns that
   are at least half as full as the fullest one: exact for a rectangle, robust to spurs). Front view: the largest
   region of shelf+box pixels gives the clear height (its z extent minus
   `racklay.layout.FRONT_CLEARANCE_PAD_M`, the 5 cm that WareSynth — and our own layouts,
   `rasterize_shelf` — add above the inter-shelf distance) and the board top (its lowest edge;
   z = 0 by the convention). A view with no region of at least `min_shelf_area_m2` counts as
   missing; a channel missing in both views is no shelf.
2. Box masks. BOX pixels inside the shelf region, cleaned by a morphological opening (a square
   kernel of `open_m` metres; at 1 pixel it does nothing, so coarse grids are left untouched),
   then split into connected components (`cv2.connectedComponentsWithStats`); components smaller
   than `min_box_area_m2` (metric area) are noise and dropped.
3. Fusion along the shared x axis. Front components whose columns overlap are one *front
   entity* (a stack seen with a gap). An entity is cut where its top edge steps by at least
   `split_step_m` (`step_segments`; touching stacks of different heights, a wall of cartons), but
   not where a top-view component starts or ends (that step is two footprints, handled below).
   Each top component is matched with the front entities its columns overlap:
   - it overlaps several (two stacks that touch in the top view but not the front view, e.g.
     bridged by a prediction): it is split by the entities' column occupancy, one piece per
     entity, pixels in gap columns are dropped, pieces below the minimum area too;
   - several top pieces share one entity (stacks that touch in the front view but not in the
     top view, or a stack hidden behind another): each piece takes the entity's height over the
     columns only it covers; a piece with no such column (fully hidden behind/in front of
     another) takes the height over all its columns and is flagged `hidden` (its height is an
     upper bound: the front view cannot see it).
   A box stack is then x-range (columns seen in both views), y-range (its top-view rows), z-range
   (median top and bottom edge of the front entity over its height columns, clipped to the
   clear height); its volume is its top-view footprint area times its height, so rotated boxes
   are not over-counted by their bounding box. Top components with no front partner and front
   entities with no top partner are reported (`unmatched_top`/`unmatched_front`), not counted.
4. Capacity = footprint (length x depth) x clear height; occupied = sum of the fused stacks'
   volumes; free = capacity - occupied, per shelf and for the rack, in m^3 and as a fraction.

Every metre <-> pixel conversion goes through `racklay.layout.Grid`.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import Sequence

import numpy as np

from . import layout as L
from .config import check_fields, option


@dataclass(frozen=True)
class ReasoningConfig:
    """Knobs of the analysis. Metric, so they mean the same thing at every grid size. Declared with
    racklay.config.option: `racklay analyze`'s flags and their help come from here."""

    open_m: float = option(0.04, "opening kernel for box masks, metres; <= 1 pixel: none (default {default})",
                           lo=0, flags=["--open-m"])
    min_box_area_m2: float = option(0.01, "box regions (either view) smaller than this are noise, m² "
                                          "(default {default})", lo=0, flags=["--min-box-area"])
    min_shelf_area_m2: float = option(0.04, "a view whose largest shelf+box region is smaller than this has no "
                                            "shelf, m² (default {default})", lo=0)
    front_pad_m: float = option(L.FRONT_CLEARANCE_PAD_M, "pad above the clear height in front views (WareSynth's "
                                                          "convention), metres", lo=0)
    connectivity: int = option(4, "pixel connectivity of components (4 keeps diagonally touching boxes apart)",
                               choices=(4, 8))
    split_step_m: float = option(0.08, "split a front-view box region into stacks where its top steps by at "
                                      "least this much, metres; 0: only gaps separate stacks (default {default})",
                                 lo=0, flags=["--split-step"])
    min_stack_m: float = option(0.1, "narrowest stack a step split may cut off, metres (default {default})",
                                lo=0, flags=["--min-stack"])
    slope_fraction: float = option(1.0, "a piece of the top edge that itself rises by at least this fraction of "
                                         "its step to its neighbours is part of a slope: the step split cuts a "
                                         "slope once, half way up, not into a staircase; 0: off (default {default})",
                                   lo=0, flags=["--slope-fraction"])
    load_width_m: float = option(0.0, "the loads' width along the shelf when they are all alike (pallets stand 0.8, "
                                      "1.0 or 1.2 m wide): each box run is cut into round(length / width) equal "
                                      "stacks instead of at its steps; 0: not known (default)",
                                 lo=0, flags=["--load-width"])

    def __post_init__(self):
        check_fields(self)


@dataclass
class BoxStack:
    """One fused box stack in its shelf's frame (metres): x along the rack, y depth, z up from
    the board top."""

    x: tuple[float, float]
    y: tuple[float, float]
    z: tuple[float, float]
    footprint_m2: float
    volume_m3: float
    #: no front-view column shows only this stack: its height is that of what hides it
    hidden: bool = False
    #: cut out of a larger top-view component along the front view's x gaps
    split: bool = False

    @property
    def size(self) -> tuple[float, float, float]:
        return (self.x[1] - self.x[0], self.y[1] - self.y[0], self.z[1] - self.z[0])

    def to_dict(self) -> dict:
        d = {k: _r(v) for k, v in asdict(self).items()}
        d["size"] = [_r(v) for v in self.size]
        return d


@dataclass
class ShelfResult:
    index: int  # layout channel (0 = lowest visible shelf)
    complete: bool  # both views present
    length_m: float = 0.0
    depth_m: float = 0.0
    clear_height_m: float = 0.0
    x: tuple[float, float] = (0.0, 0.0)  # shelf x-range, shelf frame
    y: tuple[float, float] = (0.0, 0.0)
    boxes: list[BoxStack] = field(default_factory=list)
    unmatched_top: int = 0
    unmatched_front: int = 0
    missing_view: str | None = None

    @property
    def capacity_m3(self) -> float:
        return self.length_m * self.depth_m * self.clear_height_m if self.complete else 0.0

    @property
    def occupied_m3(self) -> float:
        return float(sum(b.volume_m3 for b in self.boxes))

    @property
    def free_m3(self) -> float:
        return max(self.capacity_m3 - self.occupied_m3, 0.0)

    @property
    def free_fraction(self) -> float | None:
        return self.free_m3 / self.capacity_m3 if self.capacity_m3 > 0 else None

    def to_dict(self) -> dict:
        return {
            "index": self.index, "complete": self.complete, "missing_view": self.missing_view,
            "length_m": _r(self.length_m), "depth_m": _r(self.depth_m),
            "clear_height_m": _r(self.clear_height_m), "x": _r(self.x), "y": _r(self.y),
            "capacity_m3": _r(self.capacity_m3), "occupied_m3": _r(self.occupied_m3),
            "free_m3": _r(self.free_m3), "free_fraction": _r(self.free_fraction),
            "n_box_stacks": len(self.boxes), "unmatched_top": self.unmatched_top,
            "unmatched_front": self.unmatched_front,
            "boxes": [b.to_dict() for b in self.boxes],
        }


@dataclass
class RackResult:
    shelves: list[ShelfResult]
    grid: L.Grid
    config: ReasoningConfig = field(default_factory=ReasoningConfig)
    source: str = ""

    @property
    def n_shelves(self) -> int:
        return len(self.shelves)

    @property
    def n_box_stacks(self) -> int:
        return sum(len(s.boxes) for s in self.shelves)

    @property
    def capacity_m3(self) -> float:
        return float(sum(s.capacity_m3 for s in self.shelves))

    @property
    def occupied_m3(self) -> float:
        return float(sum(s.occupied_m3 for s in self.shelves if s.complete))

    @property
    def free_m3(self) -> float:
        return float(sum(s.free_m3 for s in self.shelves))

    @property
    def free_fraction(self) -> float | None:
        return self.free_m3 / self.capacity_m3 if self.capacity_m3 > 0 else None

    def warnings(self) -> list[str]:
        out = []
        for s in self.shelves:
            if not s.complete:
                out.append(f"shelf {s.index + 1}: no {s.missing_view}-view layout; its boxes are counted "
                           f"from one view and its volume is left out of the totals")
            if s.unmatched_top or s.unmatched_front:
                out.append(f"shelf {s.index + 1}: {s.unmatched_top} top-view and {s.unmatched_front} "
                           f"front-view box region(s) with no partner in the other view (not counted)")
        return out

    def report(self) -> str:
        """One line, as in the paper: 'Rack has 4 shelves, 12 box stacks, and 0.83 m³ of free
        space available (41%)'."""
        ns, nb = self.n_shelves, self.n_box_stacks
        frac = self.free_fraction
        pct = f" ({frac * 100:.0f}%)" if frac is not None else ""
        line = (f"Rack has {ns} {'shelf' if ns == 1 else 'shelves'}, {nb} box stack{'' if nb == 1 else 's'}, "
                f"and {self.free_m3:.2f} m³ of free space available{pct}")
        incomplete = sum(not s.complete for s in self.shelves)
        if incomplete:
            line += (f" [{incomplete} shel{'f' if incomplete == 1 else 'ves'} seen in one view only: "
                     f"not in the volume]")
        return line

    def to_dict(self) -> dict:
        return {
            "source": self.source, "report": self.report(),
            "n_shelves": self.n_shelves, "n_box_stacks": self.n_box_stacks,
            "capacity_m3": _r(self.capacity_m3), "occupied_m3": _r(self.occupied_m3),
            "free_m3": _r(self.free_m3), "free_fraction": _r(self.free_fraction),
            "grid": {"D": self.grid.size, "extent_m": self.grid.extent, "res_m": self.grid.res},
            "config": asdict(self.config), "warnings": self.warnings(),
            "shelves": [s.to_dict() for s in self.shelves],
        }

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent, ensure_ascii=False)


def _r(v, nd: int = 6):
    if v is None:
        return None
    if isinstance(v, (tuple, list)):
        return [_r(x, nd) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    return round(float(v), nd)


# --- pixel helpers ----------------------------------------------------------------------------
def clean_mask(mask: np.ndarray, grid: L.Grid, open_m: float) -> np.ndarray:
    """Morphological opening with a square kernel of `open_m` metres (no-op at <= 1 pixel)."""
    import cv2

    k = grid.m_to_px(open_m)
    m = mask.astype(np.uint8)
    if k > 1:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, np.ones((k, k), np.uint8))
    return m.astype(bool)


def components(mask: np.ndarray, grid: L.Grid, min_area_m2: float, connectivity: int = 4) -> list[np.ndarray]:
    """Boolean masks of the connected components of `mask` with a metric area >= min_area_m2,
    largest first."""
    import cv2

    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=connectivity)
    min_px = min_area_m2 / grid.pixel_area_m2()
    keep = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= min_px]
    keep.sort(key=lambda i: -stats[i, cv2.CC_STAT_AREA])
    return [lab == i for i in keep]


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(r0, r1, c0, c1) half-open bounding box of a non-empty mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _core_bbox(mask: np.ndarray, frac: float = 0.5) -> tuple[int, int, int, int]:
    """Bounding box of the rows and columns whose pixel count is at least `frac` of the fullest
    row/column: the exact rectangle for a rectangular region, and robust to spurs and ragged
    edges of a predicted one."""
    rc, cc = mask.sum(axis=1), mask.sum(axis=0)
    rows = np.flatnonzero(rc >= frac * rc.max())
    cols = np.flatnonzero(cc >= frac * cc.max())
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _region(view: np.ndarray, grid: L.Grid, cfg: ReasoningConfig) -> np.ndarray | None:
    """Largest shelf+box region of one view (cleaned), or None when there is none."""
    comps = components(clean_mask(view > 0, grid, cfg.open_m), grid, cfg.min_shelf_area_m2, 8)
    return comps[0] if comps else None


def _column_profile(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column: first row (top edge) and one past the last row (bottom edge) of `mask`;
    -1 where the column is empty."""
    D = mask.shape[0]
    any_ = mask.any(axis=0)
    top = np.where(any_, mask.argmax(axis=0), -1)
    bot = np.where(any_, D - mask[::-1].argmax(axis=0), -1)
    return top, bot


def step_segments(h: np.ndarray, step: float, min_len: int, slope_fraction: float = 0.0) -> list[tuple[int, int]]:
    """Half-open spans [a, b) cutting the 1-D profile `h` into pieces of near-constant value: the
    least-squares piecewise-constant fit with a cost of step² · min_len / 2 per extra piece (two
    pieces of min_len whose levels differ by `step` are worth cutting), every piece at least
    `min_len` long, then neighbours whose medians differ by less than `step` merged again. One
    span when nothing steps.

    With `slope_fraction` > 0 a slope is not read as a staircase (`_absorb_slopes`): a fitted piece
    that itself rises or falls by at least that fraction of its step to its neighbours, in the
    same direction, is part of a slope between two levels. The slope between two level pieces is
    cut once, where the profile crosses half way between them; a slope at an end goes to its level
    piece. A prediction's top edge blurs a step into a slope over several columns, and the fit
    alone cuts it into as many narrow pieces."""
    h = np.asarray(h, dtype=np.float64)
    n = len(h)
    if step <= 0 or n < 2 * max(min_len, 1):
        return [(0, n)]
    m = max(min_len, 1)
    c1 = np.concatenate([[0.0], np.cumsum(h)])
    c2 = np.concatenate([[0.0], np.cumsum(h * h)])
    lam = step * step * m / 2.0
    best = np.full(n + 1, np.inf)
    best[0] = -lam
    arg = np.zeros(n + 1, dtype=np.int64)
    for j in range(m, n + 1):
        i = np.arange(0, j - m + 1)
        i = i[np.isfinite(best[i])]
        if i.size == 0:
            continue
        k = j - i
        sse = (c2[j] - c2[i]) - (c1[j] - c1[i]) ** 2 / k
        tot = best[i] + sse + lam
        t = int(np.argmin(tot))
        best[j], arg[j] = tot[t], i[t]
    cuts = [n]
    while cuts[-1] > 0:
        cuts.append(int(arg[cuts[-1]]))
    spans = _merge_close(h, [(a, b) for a, b in zip(cuts[::-1][:-1], cuts[::-1][1:])], step)
    return _absorb_slopes(h, spans, step, slope_fraction) if slope_fraction > 0 else spans


def _merge_close(h: np.ndarray, spans: list[tuple[int, int]], step: float) -> list[tuple[int, int]]:
    """Neighbouring spans whose medians differ by less than `step` merged, closest pair first."""
    spans = list(spans)
    while len(spans) > 1:
        med = [float(np.median(h[a:b])) for a, b in spans]
        d = [abs(med[k + 1] - med[k]) for k in range(len(spans) - 1)]
        k = int(np.argmin(d))
        if d[k] >= step:
            break
        spans[k:k + 2] = [(spans[k][0], spans[k + 1][1])]
    return spans


def _slopes(h: np.ndarray, spans: list[tuple[int, int]], fraction: float) -> list[bool]:
    """Which spans are part of a slope: the span's own rise (its least-squares slope times its
    length: on a straight slope cut into pieces, each piece rises as much as the step between
    neighbouring pieces) has the sign of every step to its neighbours' medians and at least
    `fraction` of the smaller step. (An end span has one neighbour, so its step, median to median,
    counts its own half rise: only a short foot of a slope passes there, and a lower stack whose
    edge the prediction blurs stays a stack; on v11's predictions that finds more stacks in place
    than taking whole slopes at the ends, docs/results/2026-12-08-sixty-fourth-session.md.)"""
    med = [float(np.median(h[a:b])) for a, b in spans]
    out = []
    for i, (a, b) in enumerate(spans):
        x = np.arange(b - a, dtype=np.float64)
        x -= x.mean()
        rise = float((x * h[a:b]).sum() / max((x * x).sum(), 1e-12)) * (b - a)
        steps = ([med[i] - med[i - 1]] if i > 0 else []) + ([med[i + 1] - med[i]] if i + 1 < len(spans) else [])
        out.append(bool(steps) and all(d * rise > 0 for d in steps)
                   and abs(rise) >= fraction * min(abs(d) for d in steps))
    return out


def _absorb_slopes(h: np.ndarray, spans: list[tuple[int, int]], step: float, fraction: float) -> list[tuple[int, int]]:
    """step_segments' slope rule: each run of slope spans replaced by one cut between the level
    spans around it (or merged into the one level span beside it at an end). Every pass removes
    at least one span, so it ends."""
    while len(spans) > 1:
        slope = _slopes(h, spans, fraction)
        if not any(slope):
            return spans
        med = [float(np.median(h[a:b])) for a, b in spans]
        out, i = [], 0
        while i < len(spans):
            if not slope[i]:
                out.append(spans[i])
                i += 1
                continue
            j = i
            while j < len(spans) and slope[j]:
                j += 1
            a, b = spans[i][0], spans[j - 1][1]
            if i == 0 and j == len(spans):
                out.append((a, b))
            elif i == 0:                      # a slope at the left end: into the level after it
                out.append((a, spans[j][1]))
                j += 1
            elif j == len(spans):             # at the right end: into the level before it
                out[-1] = (out[-1][0], b)
            else:                             # between two levels: one cut, half way up
                mid = 0.5 * (med[i - 1] + med[j])
                seg = h[a:b]
                past = np.flatnonzero(seg >= mid if med[j] > med[i - 1] else seg <= mid)
                c = a + (int(past[0]) if past.size else len(seg))
                out[-1] = (out[-1][0], c)
                out.append((c, spans[j][1]))
                j += 1
            i = j
        spans = _merge_close(h, out, step)
    return spans


#: a step cut within this distance of a top-view footprint's end is that footprint's edge, metres
_EDGE_TOL_M = 0.04


def load_cuts(n_cols: int, res: float, load_width: float) -> list[int]:
    """Where a run of `n_cols` columns of `res` metres is cut into loads of about `load_width`:
    round(length / width) equal pieces, at least one (the inner cut positions, in columns)."""
    n = max(1, round(n_cols * res / load_width))
    return sorted({round(k * n_cols / n) for k in range(1, n)} - {0, n_cols})


def _split_entity(e: dict, grid: L.Grid, cfg: ReasoningConfig, top_edges: np.ndarray) -> list[dict]:
    """A front entity cut where its top edge steps (step_segments on the top profile), one entity
    per piece; the entity itself when nothing steps or splitting is off. A cut where a top-view
    footprint starts or ends (`top_edges`, columns) is not made: separate footprints already explain
    that step (a taller stack behind a shorter one), and the fusion gives each its own columns.
    With `load_width_m` each run is cut into loads of that width instead (`load_cuts`)."""
    cols = np.flatnonzero(e["cols"])
    if (cfg.split_step_m <= 0 and cfg.load_width_m <= 0) or cols.size == 0:
        return [e]
    tol = grid.m_to_px(_EDGE_TOL_M)
    out = []
    for run in np.split(cols, np.flatnonzero(np.diff(cols) > 1) + 1):
        if cfg.load_width_m > 0:
            cuts = load_cuts(len(run), grid.res, cfg.load_width_m)
        else:
            spans = step_segments(e["top"][run] * grid.res, cfg.split_step_m, grid.m_to_px(cfg.min_stack_m),
                                  cfg.slope_fraction)
            cuts = [b for _, b in spans[:-1] if not (np.abs(top_edges - run[b]) <= tol).any()]
        for a, b in zip([0] + cuts, cuts + [len(run)]):
            c = np.zeros_like(e["cols"])
            c[run[a:b]] = True
            out.append({**e, "cols": c, "pieces": []})
    return out


def _groups(n: int, linked) -> list[list[int]]:
    """Indices 0..n-1 grouped transitively by the predicate linked(i, j) (union-find)."""
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            if linked(i, j):
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values())


def _union_overlapping(col_sets: list[np.ndarray]) -> list[list[int]]:
    """Group indices whose boolean column sets overlap (transitively)."""
    return _groups(len(col_sets), lambda i, j: bool((col_sets[i] & col_sets[j]).any()))


# --- one shelf --------------------------------------------------------------------------------
def analyze_shelf(top: np.ndarray | None, front: np.ndarray | None, grid: L.Grid,
                  cfg: ReasoningConfig = ReasoningConfig(), index: int = 0) -> ShelfResult | None:
    """Analyse one shelf from its D x D class-id top and front layouts (either may be None).
    Returns None when neither view shows a shelf (a missing channel)."""
    D = grid.size
    for name, v in (("top", top), ("front", front)):
        if v is not None and np.asarray(v).shape != (D, D):
            raise L.LayoutError(f"{name} layout of shelf {index + 1}: shape {np.asarray(v).shape}, "
                                f"expected ({D}, {D}) for the grid")
    t_reg = _region(np.asarray(top), grid, cfg) if top is not None else None
    f_reg = _region(np.asarray(front), grid, cfg) if front is not None else None
    if t_reg is None and f_reg is None:
        return None
    res = ShelfResult(index=index, complete=t_reg is not None and f_reg is not None)
    if not res.complete:
        res.missing_view = "front" if f_reg is None else "top"

    t_boxes: list[np.ndarray] = []
    if t_reg is not None:
        r0, r1, c0, c1 = _core_bbox(t_reg)
        res.x = grid.col_span_to_x(c0, c1)
        res.y = grid.row_span_to_v(r0, r1)
        res.length_m = res.x[1] - res.x[0]
        res.depth_m = res.y[1] - res.y[0]
        inside = np.zeros((D, D), bool)
        inside[r0:r1, c0:c1] = True
        t_boxes = components(clean_mask((np.asarray(top) == L.BOX) & inside, grid, cfg.open_m), grid,
                             cfg.min_box_area_m2, cfg.connectivity)
    f_boxes: list[np.ndarray] = []
    z_base = 0.0
    if f_reg is not None:
        r0, r1, c0, c1 = _core_bbox(f_reg)
        z_lo, z_hi = grid.row_span_to_v(r0, r1)
        z_base = z_lo
        res.clear_height_m = max(z_hi - z_lo - cfg.front_pad_m, 0.0)
        if t_reg is None:
            res.x = grid.col_span_to_x(c0, c1)
            res.length_m = res.x[1] - res.x[0]
        inside = np.zeros((D, D), bool)
        inside[r0:r1, c0:c1] = True
        f_boxes = components(clean_mask((np.asarray(front) == L.BOX) & inside, grid, cfg.open_m), grid,
                             cfg.min_box_area_m2, cfg.connectivity)

    if not res.complete:
        # one view only: count its components (front: cut where their top steps) as stacks, no volume
        if t_reg is not None:
            res.boxes = [_one_view_box(m, grid) for m in t_boxes]
        else:
            res.boxes = [_front_only_box(e, grid, z_base) for e in _front_entities(f_boxes, grid, cfg)]
        return res

    res.boxes, res.unmatched_top, res.unmatched_front = fuse_views(t_boxes, f_boxes, grid, cfg, z_base,
                                                                   res.clear_height_m)
    return res


def _one_view_box(mask, grid) -> BoxStack:
    """A top-view component alone: its footprint, no height."""
    r0, r1, c0, c1 = _bbox(mask)
    return BoxStack(x=grid.col_span_to_x(c0, c1), y=grid.row_span_to_v(r0, r1), z=(0.0, 0.0),
                    footprint_m2=L.layout_area_m2(mask, grid), volume_m3=0.0)


def _entity_z(e: dict, cols: np.ndarray, grid: L.Grid) -> tuple[float, float]:
    """Median top and bottom edge (metres) of a front entity over the given columns (robust to
    ragged predicted tops)."""
    idx = np.flatnonzero(cols)
    return grid.row_span_to_v(int(np.floor(np.median(e["top"][idx]))), int(np.ceil(np.median(e["bot"][idx]))))


def _front_only_box(e: dict, grid: L.Grid, z_base: float) -> BoxStack:
    """A front entity alone: its x-range and height, no footprint."""
    z0, z1 = _entity_z(e, e["cols"], grid)
    c = np.flatnonzero(e["cols"])
    return BoxStack(x=grid.col_span_to_x(int(c[0]), int(c[-1]) + 1), y=(0.0, 0.0),
                    z=(max(z0 - z_base, 0.0), z1 - z_base), footprint_m2=0.0, volume_m3=0.0)


def _front_entities(f_boxes: Sequence[np.ndarray], grid: L.Grid, cfg: ReasoningConfig,
                    t_boxes: Sequence[np.ndarray] = ()) -> list[dict]:
    """Front entities: front components whose columns overlap (a stack seen with a gap), each cut
    where its top steps (_split_entity; not at the ends of the top view's footprints `t_boxes`).
    Each: {"cols": (D,) bool, "top"/"bot": per-column edge rows, "pieces": []}."""
    D = grid.size
    f_cols = [m.any(axis=0) for m in f_boxes]
    top_edges = []
    for t in t_boxes:
        c = np.flatnonzero(t.any(axis=0))
        top_edges += [c[0], c[-1] + 1]
    top_edges = np.array(top_edges)
    entities = []
    for group in _union_overlapping(f_cols):
        m = np.zeros((D, D), bool)
        for j in group:
            m |= f_boxes[j]
        top_row, bot_row = _column_profile(m)
        entities += _split_entity({"cols": m.any(axis=0), "top": top_row, "bot": bot_row, "pieces": []}, grid, cfg,
                                  top_edges)
    return entities


def fuse_views(t_boxes: Sequence[np.ndarray], f_boxes: Sequence[np.ndarray], grid: L.Grid,
               cfg: ReasoningConfig = ReasoningConfig(), z_base: float = 0.0,
               clear_height: float = np.inf) -> tuple[list[BoxStack], int, int]:
    """Fuse top-view and front-view box components of one shelf into 3D box stacks along the
    shared x axis (see the module docstring). Returns (stacks, unmatched_top, unmatched_front)."""
    D = grid.size
    min_px = cfg.min_box_area_m2 / grid.pixel_area_m2()
    entities = _front_entities(f_boxes, grid, cfg, t_boxes)

    unmatched_top = 0
    for t in t_boxes:
        tc = t.any(axis=0)
        hits = [e for e in entities if (e["cols"] & tc).any()]
        if not hits:
            unmatched_top += 1
            continue
        if len(hits) == 1:
            hits[0]["pieces"].append((t, False))
            continue
        pieces = [(e, t & e["cols"][None, :]) for e in hits]
        kept = [(e, p) for e, p in pieces if p.sum() >= min_px]  # drop bridges / slivers in gaps
        if not kept:  # only slivers: the whole footprint goes with its largest overlap
            e = max(pieces, key=lambda ep: int(ep[1].sum()))[0]
            kept = [(e, t)]
        for e, p in kept:
            e["pieces"].append((p, len(kept) > 1))

    stacks: list[BoxStack] = []
    unmatched_front = 0
    for e in entities:
        if not e["pieces"]:
            unmatched_front += 1
            continue
        piece_cols = [p.any(axis=0) & e["cols"] for p, _ in e["pieces"]]
        for k, (piece, split) in enumerate(e["pieces"]):
            cols = piece_cols[k]
            others = np.zeros(D, bool)
            for j, oc in enumerate(piece_cols):
                if j != k:
                    others |= oc
            own = cols & ~others
            hidden = not own.any()
            z0, z1 = _entity_z(e, cols if hidden else own, grid)
            z0, z1 = max(z0 - z_base, 0.0), min(z1 - z_base, clear_height)
            fp = piece & cols[None, :]
            r0, r1, c0, c1 = _bbox(fp)
            area = L.layout_area_m2(fp, grid)
            height = max(z1 - z0, 0.0)
            stacks.append(BoxStack(x=grid.col_span_to_x(c0, c1), y=grid.row_span_to_v(r0, r1),
                                   z=(z0, z0 + height), footprint_m2=area, volume_m3=area * height,
                                   hidden=hidden, split=split))
    stacks.sort(key=lambda b: (b.x[0], b.y[0]))
    return stacks, unmatched_top, unmatched_front


# --- a whole rack -----------------------------------------------------------------------------
def analyze_layouts(top: np.ndarray | None, front: np.ndarray | None, grid: L.Grid | None = None,
                    cfg: ReasoningConfig = ReasoningConfig(), source: str = "") -> RackResult:
    """Analyse R x D x D class-id layout stacks (channel 0 = lowest shelf; either may be None).
    `grid` defaults to Grid(D) with the default 8 m extent."""
    stacks = [np.asarray(s) for s in (top, front) if s is not None]
    if not stacks:
        raise ValueError(f"{source or 'layouts'}: need a top and/or a front layout stack")
    for name, s in (("top", top), ("front", front)):
        if s is not None:
            L.check_stack(np.asarray(s), encoded=False, source=f"{source or 'layouts'} ({name})")
    if top is not None and front is not None and np.shape(top) != np.shape(front):
        raise L.LayoutError(f"{source or 'layouts'}: top {np.shape(top)} and front {np.shape(front)} differ in shape")
    R, D = stacks[0].shape[0], stacks[0].shape[-1]
    grid = grid or L.Grid(D)
    if grid.size != D:
        raise L.LayoutError(f"{source or 'layouts'}: {D}x{D} layouts but the grid has D={grid.size}")
    shelves = []
    for i in range(R):
        s = analyze_shelf(None if top is None else top[i], None if front is None else front[i], grid, cfg, i)
        if s is not None:
            shelves.append(s)
    return RackResult(shelves=shelves, grid=grid, config=cfg, source=source)




# --- ground truth from 3D boxes (validation) --------------------------------------------------
def group_stacks(boxes: Sequence[L.Box], tol: float = 1e-6) -> list[list[int]]:
    """Indices of `boxes` grouped into stacks: boxes whose footprints (x/y ranges) overlap are
    one stack (stacked items stand on each other), transitively."""
    rng = [(b.x_range(), b.y_range()) for b in boxes]

    def overlap(i, j):
        (ax, ay), (bx, by) = rng[i], rng[j]
        return min(ax[1], bx[1]) - max(ax[0], bx[0]) > tol and min(ay[1], by[1]) - max(ay[0], by[0]) > tol

    return _groups(len(boxes), overlap)


@dataclass
class ShelfTruth:
    """What a shelf really holds: capacity from its metric size, occupied from its boxes."""

    shelf: L.Shelf
    boxes: list

    @property
    def n_stacks(self) -> int:
        return len(group_stacks(self.boxes))

    @property
    def capacity_m3(self) -> float:
        return self.shelf.length * self.shelf.depth * self.shelf.clear_height

    @property
    def occupied_m3(self) -> float:
        return float(sum(b.sx * b.sy * b.sz for b in self.boxes))

    @property
    def free_m3(self) -> float:
        return self.capacity_m3 - self.occupied_m3


__all__ = ["ReasoningConfig", "BoxStack", "ShelfResult", "RackResult", "clean_mask", "components",
           "analyze_shelf", "fuse_views", "analyze_layouts", "group_stacks", "ShelfTruth"]
