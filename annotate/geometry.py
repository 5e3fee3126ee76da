"""From clicks in the photo to metric shelves and boxes, and back.

The rack's front face is a plane. Four clicked corners and the rack's width W and height H give
the homography between image pixels and plane coordinates (u, v) in metres: u from the rack's
left edge to the right (0..W), v from the rack's bottom up (0..H). Oblique photos work because a
homography is exact for a plane.

* Shelf: a click on a board's front edge -> its height v on the plane. Shelves are ordered
  bottom-up; the clear height of each is the distance to the next one, the top one's is up to
  the rack's top.
* Box: two opposite corners of the box's (or stack's) front face -> a metric x-range and
  z-range on the plane -> the shelf it stands on (the highest board at or below its bottom, with
  a snap tolerance; its bottom is put on that board unless the box says on_board: false) -> a
  racklay.layout.Box in that shelf's frame: x_shelf = u - W/2 (racklay.layout.u_to_x), and a box with front offset o and
  depth d spans y in [-depth/2 + o, -depth/2 + o + d]. Its top may rise above the next board.
* Depth by clicking: the camera is recovered from the rack-plane homography (square pixels in
  the photo as taken, given the project's pixel aspect; principal point at the photo's centre,
  focal length from the homography when the view is oblique enough); a click on a box's
  top-back edge then gives its depth, a click on the board where the box's front stands gives
  its front offset.
* Layouts: racklay.layout.rasterize_shelf and stack_shelves only; nothing is re-drawn here.
* Back-projection: metric boxes and shelves -> polygon outlines in the photo.
* Model proposals: connected components of predicted front-view boxes -> metric rectangles
  (racklay.layout.Grid) -> pixel rectangles on the photo.

Assumption: a box's front face lies in the rack's front plane (front offset 0). A box set back
by o metres appears slightly smaller/higher in the photo; the error is about o / camera distance.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from racklay import layout as L
from racklay.camera import PinholeCamera
from racklay.config import check_fields, option
from racklay.data import SPAN_AT_CLEAR_HEIGHT


class GeometryError(ValueError):
    """Clicks that do not define a rack (too few corners, degenerate quadrilateral, ...)."""


def order_corners(pts) -> np.ndarray:
    """Four clicked corners in any order -> (top-left, top-right, bottom-right, bottom-left) in
    image coordinates (y down)."""
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    if p.shape[0] != 4:
        raise GeometryError(f"need 4 rack corners, have {p.shape[0]}")
    c = p.mean(axis=0)
    ang = np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0])
    p = p[np.argsort(ang)]  # clockwise on screen (y down), starting anywhere
    start = int(np.argmin(p[:, 0] + p[:, 1]))  # top-left: smallest x + y
    return np.roll(p, -start, axis=0)


def polygon_area(q) -> float:
    """Signed area of a polygon given as (n, 2) points (the shoelace formula)."""
    q = np.asarray(q, dtype=np.float64)
    x, y = q[:, 0], q[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


@dataclass
class RackPlane:
    """Homographies between image pixels and the rack's front plane (metres)."""

    corners: np.ndarray  # (4, 2) TL, TR, BR, BL in pixels
    width: float
    height: float
    H: np.ndarray = field(repr=False)  # image -> plane
    Hinv: np.ndarray = field(repr=False)  # plane -> image

    @classmethod
    def from_corners(cls, corners, width: float, height: float) -> "RackPlane":
        import cv2

        if not (width and width > 0 and height and height > 0):
            raise GeometryError(f"rack width and height must be positive metres, got {width} x {height}")
        q = order_corners(corners)
        if abs(polygon_area(q)) < 25.0:
            raise GeometryError("the 4 rack corners are (nearly) on one line: click the corners of the rack's front face")
        dst = np.array([[0, height], [width, height], [width, 0], [0, 0]], dtype=np.float64)
        H = cv2.getPerspectiveTransform(q.astype(np.float32), dst.astype(np.float32)).astype(np.float64)
        # a self-intersecting quadrilateral maps some corner behind the camera: refuse it
        hom = np.c_[q, np.ones(4)] @ H.T
        if np.any(np.sign(hom[:, 2]) != np.sign(hom[0, 2])):
            raise GeometryError("the 4 rack corners do not form a convex quadrilateral")
        return cls(q, float(width), float(height), H, np.linalg.inv(H))

    def to_plane(self, pts) -> np.ndarray:
        return _apply(self.H, pts)

    def to_image(self, pts) -> np.ndarray:
        return _apply(self.Hinv, pts)


def _apply(H: np.ndarray, pts) -> np.ndarray:
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    h = np.c_[p, np.ones(len(p))] @ H.T
    return h[:, :2] / h[:, 2:3]


# --- the metric scene ----------------------------------------------------------------------
@dataclass
class MetricBox:
    """A box in rack-plane metres: x-range [u0, u1) from the rack's left edge, bottom and top
    heights v0 < v1 from the rack's bottom, depth and front offset, and the shelf index it
    stands on (bottom-up, None when below every shelf)."""

    id: int
    u0: float
    u1: float
    v0: float
    v1: float
    depth: float
    front_offset: float
    shelf: int | None
    z0: float = 0.0  # height of its bottom above the shelf's board


@dataclass
class Scene:
    plane: RackPlane
    depth: float
    shelf_v: list[float]  # board heights, bottom-up
    shelf_ids: list[int]  # annotation ids in the same order
    clear: list[float]  # clear heights, bottom-up
    boxes: list[MetricBox]
    warnings: list[str]

    @property
    def width(self) -> float:
        return self.plane.width

    def shelves(self) -> list[L.Shelf]:
        return [L.Shelf(self.width, self.depth, c) for c in self.clear]

    def layout_boxes(self, i: int) -> list[L.Box]:
        """racklay.layout.Box objects standing on shelf i (bottom-up index), in its frame."""
        out = []
        for b in self.boxes:
            if b.shelf != i:
                continue
            y0 = L.offset_to_y(b.front_offset, self.depth)
            out.append(L.Box(cx=L.u_to_x((b.u0 + b.u1) / 2, self.width), cy=y0 + b.depth / 2,
                             sx=b.u1 - b.u0, sy=b.depth, sz=b.v1 - b.v0, z0=b.z0))
        return out

    def level_spans(self, image_width: float, at: float = SPAN_AT_CLEAR_HEIGHT) -> list[list[float]]:
        """Where each level (bottom-up) lies across the photo: the image x of the rack's left and
        right ends at `at` of the level's clear height above its board, in image widths (0 the
        left edge, 1 the right; outside [0, 1] where the rack leaves the frame), left end first.
        A struct model reads each shelf from such a span (`racklay.structure.placement_loss`)."""
        out = []
        for v, c in zip(self.shelf_v, self.clear):
            h = v + at * c
            xs = self.plane.to_image([[0.0, h], [self.width, h]])[:, 0] / float(image_width)
            out.append([float(xs.min()), float(xs.max())])
        return out

    def layouts(self, R: int, grid: L.Grid) -> tuple[np.ndarray, np.ndarray]:
        """Class-id stacks (R, D, D) for top and front views, lowest shelf first."""
        shelves = self.shelves()
        if len(shelves) > R:
            raise GeometryError(f"{len(shelves)} shelves marked but the project has R={R} channels")
        per = [L.rasterize_shelf(s, self.layout_boxes(i), grid) for i, s in enumerate(shelves)]
        return L.stack_shelves(per, R, grid)


MIN_CLEAR_M = 0.02


def shelf_heights(plane: RackPlane, points) -> tuple[np.ndarray, np.ndarray]:
    """Board heights of clicked shelf-edge points, and the order that sorts them bottom-up."""
    if len(points) == 0:
        return np.zeros(0), np.zeros(0, dtype=int)
    v = plane.to_plane(points)[:, 1]
    order = np.argsort(v, kind="stable")
    return v, order


def box_snap(settings: dict) -> float:
    """The project's box snap in metres (`project.json` box_snap; unset 0.05, null 0): how far a box
    side or bottom may lie from a rack end or board and still be drawn on it (`metric_box`, `snap_edges`)."""
    return settings.get("box_snap", 0.05) or 0.0


def build_scene(ann: dict, settings: dict) -> Scene:
    """The metric scene of an annotation (needs 4 corners and rack width/height/depth)."""
    rack = ann["rack"]
    if len(rack["corners"]) != 4:
        raise GeometryError(f"{len(rack['corners'])} of 4 rack corners set")
    if not rack.get("depth"):
        raise GeometryError("rack depth not set")
    plane = RackPlane.from_corners(rack["corners"], rack["width"], rack["height"])
    warnings: list[str] = []
    v, order = shelf_heights(plane, [s["point"] for s in ann["shelves"]])
    shelf_v = [float(v[i]) for i in order]
    shelf_ids = [ann["shelves"][i]["id"] for i in order]
    clear = []
    for k, z in enumerate(shelf_v):
        top = shelf_v[k + 1] if k + 1 < len(shelf_v) else plane.height
        c = top - z
        if c < MIN_CLEAR_M:
            warnings.append(f"shelf {k + 1}: clear height {c:.3f} m is too small (shelf at/above the next one or the rack top)")
            c = MIN_CLEAR_M
        clear.append(c)
    default_depth = settings.get("default_depth") or rack["depth"]
    snap = box_snap(settings)
    boxes = [metric_box(plane, b, shelf_v, rack["depth"], default_depth, snap, warnings) for b in ann["boxes"]]
    snap_edges(boxes, plane.width, snap)
    return Scene(plane, float(rack["depth"]), shelf_v, shelf_ids, clear, boxes, warnings)


def metric_box(plane: RackPlane, b: dict, shelf_v, rack_depth: float, default_depth: float,
               snap: float = 0.05, warnings: list | None = None) -> MetricBox:
    """A box annotation (two opposite pixel corners of its front face) -> MetricBox."""
    uv = plane.to_plane([b["p0"], b["p1"]])
    u0, u1 = sorted(np.clip(uv[:, 0], 0.0, plane.width))
    v0, v1 = sorted(uv[:, 1])
    depth = float(b.get("depth") or default_depth)
    off = float(b.get("front_offset") or 0.0)
    if off + depth > rack_depth + 1e-9:
        depth = max(rack_depth - off, 0.01)
        if warnings is not None:
            warnings.append(f"box {b['id']}: front offset + depth exceed the rack depth; depth cut to {depth:.2f} m")
    shelf = None
    z0 = 0.0
    for i in range(len(shelf_v) - 1, -1, -1):
        if v0 >= shelf_v[i] - snap:
            shelf = i
            z0 = max(v0 - shelf_v[i], 0.0)
            # a box stands on its board unless the labeller says it does not (on_board: false):
            # a box set back on the shelf looks higher than the board edge in the photo
            if z0 <= snap or b.get("on_board", True):
                z0 = 0.0
            break
    if shelf is None and warnings is not None:
        warnings.append(f"box {b['id']}: below every marked shelf; not in any layout")
    if u1 - u0 <= 0 or v1 - v0 <= 0:
        if warnings is not None:
            warnings.append(f"box {b['id']}: empty rectangle")
        shelf = None
    # the box's height counts from where it stands
    return MetricBox(int(b["id"]), float(u0), float(u1), float(v0) if shelf is None else shelf_v[shelf] + z0,
                     float(v1), depth, off, shelf, z0)


def snap_edges(boxes: list[MetricBox], width: float, snap: float) -> None:
    """Edges a labeller clicks roughly, made exact (in place): a side within `snap` metres of the
    rack's left or right edge moves onto it, and two side-by-side boxes on one shelf that overlap
    by at most `snap` meet halfway. Gaps are kept, however small: cartons 1-4 cm apart are separate
    boxes in the layouts, and closing the gap would merge them."""
    for b in boxes:
        if b.shelf is None:
            continue
        if b.u0 < snap:
            b.u0 = 0.0
        if width - b.u1 < snap:
            b.u1 = width
    on = sorted((b for b in boxes if b.shelf is not None), key=lambda b: (b.shelf, b.u0))
    for i, a in enumerate(on):
        for b in on[i + 1:]:
            if b.shelf != a.shelf:
                break
            overlap = a.u1 - b.u0
            side_by_side = min(a.v1, b.v1) > max(a.v0, b.v0)    # not one stacked on the other
            if 0 < overlap <= snap and b.u1 > a.u1 and side_by_side:
                a.u1 = b.u0 = (a.u1 + b.u0) / 2


# --- the camera, from the rack plane: box depth and front offset by clicking -----------------
@dataclass
class Camera(PinholeCamera):
    """A pinhole camera (racklay.camera.PinholeCamera) in the rack's frame: x along the rack (u),
    y into the rack (depth, away from the camera), z up (v); `center` and `ray` in that frame."""

    focal_from_photo: bool = True  # False: the view is too frontal; a typical phone focal length is assumed


#: focal length (in pixels, per pixel of the photo's longer side) assumed when a near-frontal
#: view does not determine it: a phone's main camera, about 65 degrees across the longer side
DEFAULT_FOCAL = 0.8


def camera_from_plane(plane: RackPlane, image_size, pixel_aspect: float = 1.0) -> Camera:
    """The camera that sees the rack's front plane through `plane`'s homography (Zhang's
    constraints with the principal point at the photo's centre and square pixels in the photo
    as taken: `pixel_aspect` is the width / height of one stored pixel, > 1 for a photo squeezed
    horizontally, e.g. 16/9 for a 16:9 frame stored as a square). The camera maps to stored pixels."""
    W, Hh = image_size
    a = float(pixel_aspect)
    cx, cy = (W - 1) / 2, (Hh - 1) / 2
    T = np.array([[a, 0, -a * cx], [0, 1, -cy], [0, 0, 1.0]])   # stored pixel -> centred, as taken
    M = T @ plane.Hinv  # plane (u, v, 1) -> centred image
    h1, h2 = M[:, 0], M[:, 1]
    cands = []
    with np.errstate(divide="ignore", invalid="ignore"):
        f2a = -(h1[0] * h2[0] + h1[1] * h2[1]) / (h1[2] * h2[2])
        f2b = (h2[0] ** 2 + h2[1] ** 2 - h1[0] ** 2 - h1[1] ** 2) / (h1[2] ** 2 - h2[2] ** 2)
    side = float(max(W * a, Hh))
    for f2 in (f2a, f2b):
        if np.isfinite(f2) and f2 > 0 and 0.3 * side <= np.sqrt(f2) <= 5 * side:
            cands.append(np.sqrt(f2))
    found = bool(cands)
    f = float(np.median(cands)) if found else DEFAULT_FOCAL * side
    K = np.array([[f / a, 0, cx], [0, f, cy], [0, 0, 1.0]])
    B = np.linalg.solve(K, plane.Hinv)  # ~ [r_x, r_z, t]
    lam = 2.0 / (np.linalg.norm(B[:, 0]) + np.linalg.norm(B[:, 1]))
    if B[2, 2] * lam < 0:
        lam = -lam
    rx, rz, t = B[:, 0] * lam, B[:, 1] * lam, B[:, 2] * lam
    rx /= np.linalg.norm(rx)
    rz = rz - rx * np.dot(rx, rz)
    rz /= np.linalg.norm(rz)
    ry = np.cross(rz, rx)  # x, y, z right-handed: y = z cross x
    R = np.stack([rx, ry, rz], axis=1)
    if (-R.T @ t)[1] > 0:  # the camera must be in front of the rack (y < 0)
        R[:, 1] = -R[:, 1]
    return Camera(K, R, t, found)


def depth_from_click(cam: Camera, b: MetricBox, pt, max_depth: float) -> float:
    """How far back (from the rack's front plane) the top-back edge of box b lies when the click
    `pt` is on it: the depth s whose projected edge {(u, s, b.v1)} passes closest to the click."""
    s = np.linspace(0.0, max(max_depth, 0.01) * 1.5, 1201)
    ends = []
    for u in (b.u0, b.u1):
        ends.append(cam.project(np.stack([np.full_like(s, u), s, np.full_like(s, b.v1)], axis=1)))
    a, c = ends
    d = c - a
    p = np.asarray(pt, dtype=np.float64)[None, :]
    dist = np.abs(d[:, 0] * (p[:, 1] - a[:, 1]) - d[:, 1] * (p[:, 0] - a[:, 0])) / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    return float(s[int(np.argmin(dist))])


def offset_from_click(cam: Camera, board_v: float, pt) -> float | None:
    """How far back from the rack's front plane the click `pt` is, on the board at height
    board_v (where a set-back box's front stands); None when the ray misses the board's top."""
    c, d = cam.ray(pt)
    if abs(d[2]) < 1e-12:
        return None
    lam = (board_v - c[2]) / d[2]
    if lam <= 0:
        return None
    return float(c[1] + lam * d[1])


#: a labelled box whose front face comes this close (pixels) to the photo's left / right (top /
#: bottom) edge is cut by the frame: the photo shows only part of its width (height)
FRAME_MARGIN_PX = 3.0


def cut_by_frame(plane: RackPlane, box: MetricBox, image_size) -> tuple[bool, bool]:
    """(width cut, height cut): whether the photo's frame cuts a labelled box's front face at its
    left or right edge (top or bottom edge), so that its visible width (height) is not its size."""
    w, h = image_size
    px = plane.to_image([[box.u0, box.v0], [box.u1, box.v0], [box.u1, box.v1], [box.u0, box.v1]])
    m = FRAME_MARGIN_PX
    return (bool((px[:, 0] <= m).any() or (px[:, 0] >= w - m).any()),
            bool((px[:, 1] <= m).any() or (px[:, 1] >= h - m).any()))


def restore_aspect(image: np.ndarray, pixel_aspect: float) -> np.ndarray:
    """A photo stored with non-square pixels resized to its aspect as taken (width x
    `pixel_aspect`, height kept); itself when the pixels are square."""
    if abs(float(pixel_aspect) - 1.0) < 1e-6:
        return image
    import cv2

    h, w = image.shape[:2]
    return cv2.resize(image, (max(1, round(w * float(pixel_aspect))), h), interpolation=cv2.INTER_AREA
                      if pixel_aspect < 1 else cv2.INTER_LINEAR)


# --- back to the photo ---------------------------------------------------------------------
def box_outline(plane: RackPlane, b: MetricBox) -> np.ndarray:
    """(4, 2) pixel polygon of a metric box's front face."""
    return plane.to_image([[b.u0, b.v0], [b.u1, b.v0], [b.u1, b.v1], [b.u0, b.v1]])


def box_polygon(scene: Scene | None, b: dict) -> np.ndarray:
    """(4, 2) pixel polygon of a box annotation as the tool outlines and picks it: its metric
    front face mapped back to the photo when there is a scene (the box's own depth ignored),
    else the clicked rectangle."""
    if scene is not None:
        return box_outline(scene.plane, metric_box(scene.plane, b, scene.shelf_v or [-1e9], scene.depth, scene.depth))
    (x0, y0), (x1, y1) = b["p0"], b["p1"]
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)


def shelf_line(plane: RackPlane, v: float) -> np.ndarray:
    """(2, 2) pixel end points of the board edge at height v."""
    return plane.to_image([[0.0, v], [plane.width, v]])


def rect_outline(plane: RackPlane, u0: float, u1: float, v0: float, v1: float) -> np.ndarray:
    return plane.to_image([[u0, v0], [u1, v0], [u1, v1], [u0, v1]])


# --- model proposals / imported layouts -> metric rectangles --------------------------------
@dataclass
class Proposal:
    shelf: int
    u0: float
    u1: float
    v0: float
    v1: float
    depth: float | None
    front_offset: float
    score: float | None = None


def front_box_rects(front: np.ndarray, top: np.ndarray | None, grid: L.Grid, shelf_v, width: float,
                    rack_depth: float, probs_box: np.ndarray | None = None, tops=None, cfg=None) -> list[Proposal]:
    """One metric rectangle on the rack plane per box stack that the rack reasoning reads in each
    shelf's layouts (racklay.reasoning.analyze_shelf with its defaults: box regions, cut where their
    top steps, fused with the top view), so stacks that touch come out one per stack. Only shelves
    with a marked board height (shelf_v) are used. Depth and front offset come from the stack's
    top-view rows, if a top view is given. `tops` (plane heights, one per shelf) clips each
    rectangle to the space below the next board; `probs_box` (R, S, S) scores a rectangle by the mean
    box probability of its front-view box pixels; `cfg`: the reasoning's knobs (default: its defaults)."""
    from racklay.reasoning import ReasoningConfig, analyze_shelf

    centres = grid.centers()
    out = []
    for i, v in enumerate(shelf_v):
        if i >= front.shape[0]:
            break
        shelf = analyze_shelf(None if top is None else top[i], front[i], grid, cfg or ReasoningConfig(), index=i)
        if shelf is None or shelf.missing_view == "front":
            continue
        for b in shelf.boxes:
            depth, off = None, 0.0
            if shelf.complete:
                off = float(np.clip(L.y_to_offset(b.y[0], rack_depth), 0.0, rack_depth))
                depth = float(np.clip(b.y[1] - b.y[0], grid.res, rack_depth - off)) if rack_depth - off > 0 else None
            score = None
            if probs_box is not None:
                cols = (centres >= b.x[0]) & (centres < b.x[1])
                px = probs_box[i][:, cols][front[i][:, cols] == L.BOX]
                score = float(px.mean()) if px.size else None
            u0, u1 = np.clip(L.x_to_u(np.array(b.x), width), 0.0, width)
            v0, v1 = v + b.z[0], v + b.z[1]
            if tops is not None:
                v1 = min(v1, tops[i])
            if u1 <= u0 or v1 <= v0:
                continue
            out.append(Proposal(i, float(u0), float(u1), float(v0), float(v1), depth, off, score))
    return out


@dataclass
class GapSplit:
    """How a model proposal is cut where the photo shows a gap along it (`split_at_dark_gaps`).
    The gap between two loads is a narrow dark slot in the photo (the shadowed space between
    them, the rack's back); the model often reads the loads as one run. Declared with
    racklay.config.option, so each default is written once."""

    depth: float = option(0.3, "model proposals (and W) are cut where the photo along them is darker than the "
                               "light on both sides within the gap width by at least this share of its median "
                               "luminance; 0: never cut (default {default})", lo=0, flags=["--gap-depth"],
                          metavar="SHARE")
    close_m: float = option(0.3, "gap width: the widest dark slot that counts as a gap, metres; darker stretches "
                                 "wider than this are a dark load, not a gap (default {default})", gt=0,
                            flags=["--gap-width"], metavar="M")
    min_part_m: float = option(0.2, "narrowest load a cut may leave on either side, metres (default {default})",
                               lo=0, flags=["--gap-min-part"], metavar="M")
    rows: tuple = option((0.05, 0.6), "the band of the proposal's height the cue is read in, as fractions from "
                                      "its bottom (loads' lower parts: their tops may be cut by the next board)")
    step_m: float = option(0.01, "the cue is read every this many metres along the rack (default {default})", gt=0)

    def __post_init__(self):
        check_fields(self)
        lo, hi = self.rows
        if not 0 <= lo < hi <= 1:
            raise ValueError(f"option 'rows': expected 0 <= bottom < top <= 1, got {self.rows!r}")


#: image rows sampled across a proposal's band at each position along the rack
_CUE_ROWS = 16


def plane_profile(luma: np.ndarray, plane: RackPlane, u0: float, u1: float, v0: float, v1: float,
                  rows: tuple = (0.0, 1.0), step: float = 0.01, n_rows: int = _CUE_ROWS):
    """The photo's luminance along the rack: positions u every `step` metres in [u0, u1) and, at
    each, the mean of `luma` (H, W) over `n_rows` points of the plane from v0 + rows[0] (v1 - v0) to
    v0 + rows[1] (v1 - v0) (nearest pixel; NaN where fewer than a quarter of them are in the photo).
    Returns (u, value), each (n,)."""
    H, W = luma.shape
    us = np.arange(u0 + step / 2, u1, step)
    fs = np.linspace(v0 + rows[0] * (v1 - v0), v0 + rows[1] * (v1 - v0), n_rows)
    pts = plane.to_image(np.stack(np.broadcast_arrays(us[:, None], fs[None, :]), -1).reshape(-1, 2))
    xs, ys = pts[:, 0].reshape(len(us), n_rows), pts[:, 1].reshape(len(us), n_rows)
    ok = (xs >= 0) & (xs < W) & (ys >= 0) & (ys < H)
    px = luma[np.where(ok, ys, 0).astype(int), np.where(ok, xs, 0).astype(int)]
    n = ok.sum(1)
    val = np.where(n >= n_rows / 4, (px * ok).sum(1) / np.maximum(n, 1), np.nan)
    return us, val


def split_at_dark_gaps(p: Proposal, luma: np.ndarray, plane: RackPlane, cfg: GapSplit | None = None,
                       max_cuts: int = 3) -> list[Proposal]:
    """`p` cut where the photo shows a gap along it: the photo's luminance along the proposal's
    band (`plane_profile`), its black top-hat (grey closing over `cfg.close_m` minus the profile,
    over the profile's median: how much darker than the light on both sides a narrow slot is); at
    the strongest slot at least `cfg.depth` deep that leaves `cfg.min_part_m` on both sides, the
    proposal becomes two, the slot (where it is at least half as deep) left between them; each
    part again, up to `max_cuts` deep. `p` unchanged where no slot is deep enough or the photo
    does not show most of it. Measured on the labelled photos: docs/annotate.md."""
    from dataclasses import replace

    from scipy.ndimage import grey_closing

    cfg = cfg or GapSplit()
    if not cfg.depth or max_cuts <= 0 or p.u1 - p.u0 < 2 * cfg.min_part_m:
        return [p]
    us, val = plane_profile(luma, plane, p.u0, p.u1, p.v0, p.v1, cfg.rows, cfg.step_m)
    if not len(us) or np.isnan(val).mean() > 0.3:
        return [p]
    val = np.where(np.isnan(val), np.nanmedian(val), val)
    k = max(3, int(round(cfg.close_m / cfg.step_m)) | 1)
    slot = (grey_closing(val, size=k, mode="nearest") - val) / max(float(np.median(val)), 1e-6)
    inner = (us - p.u0 >= cfg.min_part_m) & (p.u1 - us >= cfg.min_part_m)
    j = int(np.argmax(np.where(inner, slot, -np.inf)))
    if not inner[j] or slot[j] < cfg.depth:
        return [p]
    lo, hi = j, j
    while lo > 0 and slot[lo - 1] >= slot[j] / 2:
        lo -= 1
    while hi < len(us) - 1 and slot[hi + 1] >= slot[j] / 2:
        hi += 1
    half = cfg.step_m / 2
    left = replace(p, u1=float(max(us[lo] - half, p.u0 + cfg.min_part_m)))
    right = replace(p, u0=float(min(us[hi] + half, p.u1 - cfg.min_part_m)))
    return (split_at_dark_gaps(left, luma, plane, cfg, max_cuts - 1)
            + split_at_dark_gaps(right, luma, plane, cfg, max_cuts - 1))


def photo_gaps(props: list[Proposal], luma: np.ndarray, plane: RackPlane,
               cfg: GapSplit | None = None) -> list[tuple[int, float, float]]:
    """Where the photo shows a gap inside a proposal (`split_at_dark_gaps`): (shelf, u0, u1) of
    every stretch left between the parts of a proposal it cuts."""
    out = []
    for p in props:
        parts = split_at_dark_gaps(p, luma, plane, cfg)
        out += [(p.shelf, a.u1, b.u0) for a, b in zip(parts, parts[1:])]
    return out


def cut_box_columns(layouts: np.ndarray, grid: L.Grid, width: float, gaps) -> np.ndarray:
    """A copy of a view's layout stack (R, D, D) with the box pixels of each gap (shelf, u0, u1)
    (rack plane, metres: the columns whose centre x = u - width / 2 lies in [u0, u1)) made free
    shelf space, as a gap between two loads is drawn: the rack reasoning then reads the loads on
    either side as stacks of their own, each with its own height."""
    out = layouts.copy()
    x = grid.centers()
    for shelf, u0, u1 in gaps:
        if shelf < len(out):
            cols = (x >= L.u_to_x(u0, width)) & (x < L.u_to_x(u1, width))
            ch = out[shelf]
            ch[:, cols] = np.where(ch[:, cols] == L.BOX, L.SHELF, ch[:, cols])
    return out


def proposal_to_box(plane: RackPlane, p: Proposal, box_id: int) -> dict:
    """A proposal as a box annotation dict (pixel corners bottom-left / top-right)."""
    px = plane.to_image([[p.u0, p.v0], [p.u1, p.v1]])
    d = {"id": int(box_id), "p0": [round(float(px[0, 0]), 2), round(float(px[0, 1]), 2)],
         "p1": [round(float(px[1, 0]), 2), round(float(px[1, 1]), 2)], "front_offset": round(p.front_offset, 4),
         "source": "model"}
    if p.depth is not None:
        d["depth"] = round(p.depth, 4)
    if p.score is not None:
        d["score"] = round(min(max(p.score, 0.0), 1.0), 4)
    return d


def rect_iou(a, b) -> float:
    """IoU of two axis-aligned rectangles (u0, u1, v0, v1)."""
    iw = max(0.0, min(a[1], b[1]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[2], b[2]))
    inter = iw * ih
    ua = (a[1] - a[0]) * (a[3] - a[2]) + (b[1] - b[0]) * (b[3] - b[2]) - inter
    return inter / ua if ua > 0 else 0.0
