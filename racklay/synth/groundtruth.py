"""Ground truth of one rendered scene. Layouts come from the scene description through
racklay.layout (rasterize_shelf / stack_shelves) only; per-pixel maps come from the exact
G-buffer; 2D/3D boxes from the scene geometry and the instance map."""
from __future__ import annotations

import math

import numpy as np

from .. import layout as L
from ..data import LEVEL_SPANS_KEY, SPAN_AT_CLEAR_HEIGHT
from .effects import distort_points
from .scene import CATEGORY_NAMES, IN_FRONT_M, SEMANTIC_CLASSES, Scene, cuboid_corners


def scene_layouts(scene: Scene, grid: L.Grid, R: int) -> tuple[np.ndarray, np.ndarray]:
    """(top, front) class-id stacks R x D x D: channel c = visible shelf c (lowest first), each
    the whole bay or, with a layout window (Recipe.layout_extent 'frame' or 'row'), the part of it
    (or of its row of bays) shown."""
    per = [L.rasterize_shelf(shelf, boxes, grid, window=scene.layout_window)
           for shelf, boxes in scene.layout_inputs()]
    return L.stack_shelves(per, R, grid)


def semantic_map(scene: Scene, instance: np.ndarray) -> np.ndarray:
    lut = np.zeros(len(scene.objects) + 1, np.uint8)
    lut[1:] = [o.semantic for o in scene.objects]
    return lut[np.minimum(instance, len(scene.objects))]


def depth_png(depth: np.ndarray) -> np.ndarray:
    """Camera-frame z in millimetres as uint16 (0 = no surface; clipped at 65.535 m)."""
    return np.clip(np.rint(depth * 1000.0), 0, 65535).astype(np.uint16)


def _r(v, nd=5):
    return [round(float(x), nd) for x in np.asarray(v).ravel()]


def _clip_area(poly: np.ndarray, W: int, H: int) -> tuple[float, float]:
    """(area of a convex polygon, area of its part inside the image)."""
    import cv2

    hull = cv2.convexHull(poly.astype(np.float32))
    area = float(cv2.contourArea(hull))
    rect = np.array([[0, 0], [W, 0], [W, H], [0, H]], np.float32)
    inter, _ = cv2.intersectConvexConvex(hull.reshape(-1, 2), rect)
    return area, float(inter)


def object_annotations(scene: Scene, instance: np.ndarray, coco: bool = True) -> list[dict]:
    """Annotations of every carton/crate that is on the considered rack or has visible pixels:
    category, shelf/channel, 3D box in world and camera frames, visible and amodal 2D boxes,
    visible pixel count and fraction, truncation, optional COCO polygons."""
    import cv2
    from scipy import ndimage

    cam = scene.camera
    W, H = cam.width, cam.height
    parts = [(i, o.part_of) for i, o in enumerate(scene.objects) if o.part_of >= 0]
    if parts:   # the pixels of a drawn part (a pallet, the cartons on it) are its load unit's
        lut = np.arange(len(scene.objects) + 1, dtype=instance.dtype)
        for i, u in parts:
            lut[i + 1] = u + 1
        instance = lut[np.minimum(instance, len(scene.objects))]
    counts = np.bincount(instance.ravel(), minlength=len(scene.objects) + 1)
    slices = ndimage.find_objects(instance.astype(np.int32), max_label=len(scene.objects))
    chan = {si: c for c, si in enumerate(scene.visible)}
    out = []
    sel = [i for i, o in enumerate(scene.objects) if o.category >= 0 and (counts[i + 1] > 0 or o.shelf >= 0)]
    all_corners = cuboid_corners([scene.objects[i] for i in sel])
    uv_all, z_all = cam.project_z(all_corners.reshape(-1, 3))
    uv_all, z_all = distort_points(cam.K, cam.k1, uv_all.reshape(-1, 8, 2)), z_all.reshape(-1, 8)
    c_cam_all = cam.to_cam(np.array([scene.objects[i].center for i in sel]).reshape(-1, 3))
    for k, i in enumerate(sel):
        o = scene.objects[i]
        iid = i + 1
        vis = int(counts[iid])
        uv, zc = uv_all[k], z_all[k]
        in_front = bool((zc > 0.05).all())
        amodal = None
        frac, trunc = 0.0, 1.0
        if in_front:
            x0, y0 = uv.min(axis=0)
            x1, y1 = uv.max(axis=0)
            area, inside = _clip_area(uv, W, H)
            trunc = 1.0 - inside / area if area > 0 else 1.0
            if x1 > 0 and y1 > 0 and x0 < W and y0 < H:
                amodal = [max(0.0, x0), max(0.0, y0), min(float(W), x1), min(float(H), y1)]
            frac = min(1.0, vis / inside) if inside > 0 else 0.0
        bbox = None
        seg = None
        sl = slices[i] if i < len(slices) else None
        if vis and sl is not None:
            ys, xs = sl
            bbox = [xs.start, ys.start, xs.stop, ys.stop]
            if coco:
                m = (instance[sl] == iid).astype(np.uint8)
                cs, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
                seg = [(c.reshape(-1, 2) + [xs.start, ys.start]).ravel().tolist() for c in cs if len(c) >= 3]
        c_world = np.array(o.center)
        c_cam = c_cam_all[k]
        heading = cam.R @ np.array([math.cos(o.yaw), math.sin(o.yaw), 0.0])
        ann = {
            "id": iid, "category": CATEGORY_NAMES[o.category], "category_id": o.category + 1,
            "semantic": SEMANTIC_CLASSES[o.semantic],
            "shelf": o.shelf if o.shelf >= 0 else None,
            "channel": chan.get(o.shelf) if o.shelf >= 0 else None,
            "size": _r(o.size), "yaw": round(o.yaw, 6),
            "center_world": _r(c_world), "center_cam": _r(c_cam),
            "rotation_y_cam": round(math.atan2(-heading[2], heading[0]), 6),
            "bbox_visible": bbox, "bbox_amodal": None if amodal is None else _r(amodal, 2),
            "visible_pixels": vis, "visible_fraction": round(frac, 4), "truncation": round(max(0.0, trunc), 4),
        }
        if o.layout_box is not None:
            b = o.layout_box
            ann["shelf_frame"] = {"cx": round(b.cx, 6), "cy": round(b.cy, 6), "z0": round(b.z0, 6)}
        if coco:
            ann["segmentation"] = seg or []
        out.append(ann)
    return out


def kitti_lines(objects: list[dict]) -> str:
    """KITTI-style label lines (type truncated occluded alpha bbox dims(h w l) loc(x y z) ry),
    camera frame = OpenCV; loc is the bottom centre of the box; only visible objects."""
    lines = []
    for a in objects:
        if a["bbox_visible"] is None:
            continue
        sx, sy, sz = a["size"]
        x, y, z = a["center_cam"]
        ry = a["rotation_y_cam"]
        vf = a["visible_fraction"]
        occ = 0 if vf > 0.8 else 1 if vf > 0.4 else 2
        # bottom centre: KITTI's y axis points down, so bottom = centre + h/2 (level camera)
        alpha = (ry - math.atan2(x, z) + math.pi) % (2 * math.pi) - math.pi
        x0, y0, x1, y1 = a["bbox_visible"]
        lines.append(f"{a['category']} {a['truncation']:.2f} {occ} {alpha:.4f} {x0:.2f} {y0:.2f} {x1:.2f} {y1:.2f} "
                     f"{sz:.4f} {sy:.4f} {sx:.4f} {x:.4f} {y + sz / 2:.4f} {z:.4f} {ry:.4f}")
    return "\n".join(lines) + ("\n" if lines else "")


def grid_meta(grid: L.Grid, recipe) -> dict:
    """The meta's "grid": the layouts' size, extent and channel count."""
    return {"D": grid.size, "extent_m": grid.extent, "R": recipe.R}


def layout_meta(scene: Scene) -> dict:
    """The meta's rack fields that depend on what the layouts draw (recipe key layout_extent)."""
    return {
        # the part of the bay the layouts draw (world x, metres; null: all of it), re-centred,
        # and per layout channel the height of its opening drawn (null: all of it)
        "layout_window": None if scene.layout_window is None else _r(scene.layout_window, 6),
        # layout_extent 'row': the row of bays (world x) the shelves continue into; null: the bay alone
        "layout_row": None if scene.layout_row is None else _r(scene.layout_row, 6),
        "layout_heights": None if scene.layout_heights is None else
        [None if h is None else round(h, 6) for h in scene.layout_heights]}


def level_spans(scene: Scene, at: float = SPAN_AT_CLEAR_HEIGHT) -> list:
    """Per layout channel (visible shelf, lowest first): where the image shows the shelf the
    layouts draw, [left, right] image x of its front edge's ends at `at` of its drawn clear height,
    in image widths (beyond [0, 1] where it leaves the frame; lens distortion applied where the
    lens model holds, the pinhole's extrapolation beyond), as `annotate export` writes a labelled
    photo's (racklay.data.level_spans); None for a level with an end behind the camera. The ends
    are the drawn part's: the layout window's, else the row's or the bay's."""
    cam, depth = scene.camera, scene.rack_depth
    out = []
    for k, (shelf, _) in enumerate(scene.layout_inputs()):
        x0, x1 = scene.layout_window if scene.layout_window is not None else (-shelf.length / 2, shelf.length / 2)
        z = scene.shelves[scene.visible[k]].board_top + at * shelf.clear_height
        uv, zc = cam.project_z([[x0, -depth / 2, z], [x1, -depth / 2, z]])
        if (zc <= IN_FRONT_M).any():
            out.append(None)
            continue
        xs = np.where(cam.lens_holds(uv), distort_points(cam.K, cam.k1, uv)[:, 0], uv[:, 0]) / cam.width
        out.append([round(float(xs.min()), 5), round(float(xs.max()), 5)])
    return out


def scene_meta(scene: Scene, recipe, grid: L.Grid, objects: list[dict]) -> dict:
    cam = scene.camera
    shelves = scene.shelves
    return {
        "source": "WareSynth (racklay synth)", "domain": scene.domain, "recipe": scene.recipe,
        "seed": scene.seed, "index": scene.index,
        "image_size": [cam.width, cam.height],
        "camera": {"K": [_r(row, 6) for row in cam.K], "R": [_r(row, 8) for row in cam.R], "t": _r(cam.t, 6),
                   "position_world": _r(cam.center, 6), "distortion_k1": round(cam.k1, 6),
                   "convention": "X_cam = R @ X_world + t; OpenCV axes (x right, y down, z forward); "
                                 "world x along the rack, y into it, z up; pixel centres at +0.5"},
        "grid": grid_meta(grid, recipe),
        "rack": {"style": scene.rack_style, "length": round(scene.rack_length, 6), "depth": round(scene.rack_depth, 6),
                 "n_shelves": len(shelves),
                 "board_tops": _r([s.board_top for s in shelves], 6),
                 "clear_heights": _r([s.clear_height for s in shelves], 6),
                 "visible_shelves": list(scene.visible), **layout_meta(scene)},
        # per layout channel (lowest visible shelf first): inter-shelf height, like WareSynth's height*.npy
        "shelf_heights": _r([shelves[i].clear_height for i in scene.visible], 6),
        "shelf_board_tops": _r([shelves[i].board_top for i in scene.visible], 6),
        # per layout channel: [left, right] of the drawn shelf across the image (image widths)
        LEVEL_SPANS_KEY: level_spans(scene),
        "background": scene.background, "occupancy_map": scene.occupancy,
        "lights": [{"position": _r(l.position, 4), "color": _r(l.color, 4), "intensity": round(l.intensity, 4)}
                   for l in scene.lights], "ambient": round(scene.ambient, 4),
                   "ambient_occlusion": round(scene.occlusion, 4),
        "effects": {k: (round(v, 5) if isinstance(v, float) else v) for k, v in scene.effects.items()},
        "semantic_classes": list(SEMANTIC_CLASSES),
        "objects": objects,
    }
