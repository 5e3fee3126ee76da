"""WareSynth ground truth agrees with the picture and with the scene geometry.

The reference for "the picture" is an independent numpy ray caster over the scene's cuboids
(written here, not shared with the renderer)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from racklay import layout as L
from racklay.synth.groundtruth import object_annotations, scene_layouts
from racklay.synth.recipe import RecipeError, load_recipe
from racklay.synth.scene import CATEGORIES, Obj, cuboid_corners, sample_scene

SMALL = {"image_width": 240, "image_height": 144, "focal_px": [170.0, 260.0]}


@pytest.fixture(scope="module")
def renderer():
    from racklay.synth.render import GLRenderer
    from racklay.synth.textures import build_bank

    r = load_recipe("complex", SMALL)
    ren = GLRenderer(build_bank(r.texture_family, 0), r.image_width, r.image_height, msaa=0)
    yield r, ren
    ren.release()


def raycast(scene, pix_uv):
    """Nearest object index and camera z for rays through pixel coordinates (N, 2)."""
    cam = scene.camera
    d_cam = np.c_[pix_uv, np.ones(len(pix_uv))] @ np.linalg.inv(cam.K).T  # z component = 1
    d = d_cam @ cam.R  # world directions (R^T d)
    o = cam.center
    best_t = np.full(len(pix_uv), np.inf)
    best_i = np.full(len(pix_uv), -1)
    for i, ob in enumerate(scene.objects):
        c, s = math.cos(-ob.yaw), math.sin(-ob.yaw)
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        ol = rot @ (o - np.array(ob.center))
        dl = d @ rot.T
        h = np.array(ob.size) / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-h - ol) / dl
            t2 = (h - ol) / dl
        tmin = np.nanmax(np.minimum(t1, t2), axis=1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (tmax >= np.maximum(tmin, 0)) & (tmin > 0) & (tmin < best_t)
        best_t[hit] = tmin[hit]
        best_i[hit] = i
    return best_i, best_t  # t along d_cam (z = 1) is the camera z


def hull_mask(uv8, W, H):
    """Pixels whose centre lies inside the convex hull of projected corners."""
    import cv2

    hull = cv2.convexHull(uv8.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    x0, y0 = np.floor(hull.min(0)).astype(int)
    x1, y1 = np.ceil(hull.max(0)).astype(int)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
    m = np.zeros((H, W), bool)
    if x0 >= x1 or y0 >= y1:
        return m
    px, py = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
    inside = np.ones(px.shape, bool)
    n = len(hull)
    area = sum(hull[k, 0] * hull[(k + 1) % n, 1] - hull[(k + 1) % n, 0] * hull[k, 1] for k in range(n))
    sgn = 1 if area > 0 else -1
    for k in range(n):
        a, b = hull[k], hull[(k + 1) % n]
        cross = (b[0] - a[0]) * (py - a[1]) - (b[1] - a[1]) * (px - a[0])
        inside &= sgn * cross >= 0
    m[y0:y1, x0:x1] = inside
    return m


def test_projected_hull_matches_instance_mask_and_depth(renderer):
    r, ren = renderer
    tested = 0
    for index in range(4):
        scene = sample_scene(r, 3, index)
        out = ren.render(scene)
        W, H = r.image_width, r.image_height
        items = [i for i, o in enumerate(scene.objects) if o.shelf >= 0]
        corners = cuboid_corners([scene.objects[i] for i in items])
        for k, i in enumerate(items):
            uv, z = scene.camera.project_z(corners[k])
            if (z <= 0.1).any() or uv[:, 0].min() < 0 or uv[:, 1].min() < 0 or uv[:, 0].max() > W or uv[:, 1].max() > H:
                continue  # only boxes fully inside the image
            hm = hull_mask(uv, W, H)
            if hm.sum() < 80:
                continue
            ys, xs = np.nonzero(hm)
            nearest, tz = raycast(scene, np.c_[xs + 0.5, ys + 0.5])
            if (nearest != i).any():
                continue  # occluded (by the independent ray caster): not part of this check
            inst = out.instance == i + 1
            iou = (hm & inst).sum() / (hm | inst).sum()
            assert iou >= 0.95, f"scene {index}, box {i}: hull/mask IoU {iou:.3f}"
            # depth at the visible faces = ray-cast distance to the box (within 1 cm)
            dz = np.abs(out.depth[ys, xs] - tz)
            interior = inst[ys, xs]
            assert dz[interior].max() < 0.01, f"scene {index}, box {i}: depth off by {dz[interior].max():.4f} m"
            tested += 1
    assert tested >= 5, f"only {tested} unoccluded boxes found to test"


def test_written_depth_png_is_millimetres(renderer):
    from racklay.synth.groundtruth import depth_png

    r, ren = renderer
    out = ren.render(sample_scene(r, 0, 0))
    mm = depth_png(out.depth)
    valid = out.depth > 0
    assert mm.dtype == np.uint16
    assert np.abs(mm[valid] / 1000.0 - out.depth[valid]).max() <= 0.0005 + 1e-6


def test_box_at_known_coordinates_lands_on_the_right_layout_pixels():
    r = load_recipe("complex")
    scene = sample_scene(r, 5, 11)
    assert 1 <= len(scene.visible) <= r.R
    grid = L.Grid(512, 8.0)
    target = scene.visible[-1]
    # clear every shelf, then put one known box on the highest visible shelf
    for sh in scene.shelves:
        sh.items = []
    b = L.Box(cx=0.30, cy=-0.10, sx=0.40, sy=0.30, sz=0.25, z0=0.0, yaw=0.0)
    z_board = scene.shelves[target].board_top
    scene.objects.append(Obj((0.30, -0.10, z_board + 0.125), (0.40, 0.30, 0.25), 0.0, "carton_small", 5,
                             category=0, shelf=target, layout_box=b))
    scene.shelves[target].items = [len(scene.objects) - 1]
    top, front = scene_layouts(scene, grid, r.R)
    c = len(scene.visible) - 1
    # pixels whose centre lies inside the box (the convention's rule)
    xc, yc = grid.centers(), grid.row_centers()
    cols = np.nonzero((xc >= 0.10) & (xc < 0.50))[0]
    rows = np.nonzero((yc >= -0.25) & (yc < 0.05))[0]
    assert len(cols) == round(0.40 / grid.res) and len(rows) == round(0.30 / grid.res)
    assert cols[0] == 256 + round(0.10 / grid.res) and rows[0] == 256 - round(0.05 / grid.res)
    assert (top[c][np.ix_(rows, cols)] == L.BOX).all()
    assert (top[c] == L.BOX).sum() == len(rows) * len(cols)
    frows = np.nonzero((yc >= 0.0) & (yc < 0.25))[0]  # z rows: board top on the centre boundary, up is up
    assert frows[-1] == 255 and len(frows) == 16
    assert (front[c][np.ix_(frows, cols)] == L.BOX).all()
    assert (front[c] == L.BOX).sum() == len(frows) * len(cols)
    # the shelf itself: length x depth in the top view, length x (clear height + 5 cm) in front
    sh = scene.shelves[target]
    assert (top[c] != L.BACKGROUND).sum() == L.fill_axis_rect(np.zeros((512, 512), np.uint8), grid,
        -scene.rack_length / 2, scene.rack_length / 2, -scene.rack_depth / 2, scene.rack_depth / 2, 1).sum()
    assert (front[c] != L.BACKGROUND).sum() == L.fill_axis_rect(np.zeros((512, 512), np.uint8), grid,
        -scene.rack_length / 2, scene.rack_length / 2, 0, sh.clear_height + L.FRONT_CLEARANCE_PAD_M, 1).sum()
    # empty visible shelves: shelf pixels, no box pixels; missing channels: all zero
    for k in range(len(scene.visible) - 1):
        assert (top[k] == L.BOX).sum() == 0 and (front[k] == L.BOX).sum() == 0
        assert (top[k] == L.SHELF).sum() > 0
    for k in range(len(scene.visible), r.R):
        assert not top[k].any() and not front[k].any()


def _footprints_overlap(a: L.Box, b: L.Box) -> bool:
    """Separating-axis test of two rotated rectangles (shelf frame, top view)."""
    pa, pb = a.corners_xy(), b.corners_xy()
    for poly in (pa, pb):
        for k in range(4):
            e = poly[(k + 1) % 4] - poly[k]
            n = np.array([-e[1], e[0]])
            sa, sb = pa @ n, pb @ n
            if sa.max() <= sb.min() + 1e-9 or sb.max() <= sa.min() + 1e-9:
                return False
    return True


@pytest.mark.parametrize("recipe", ["simple", "complex", "proxy_real", "complex_paper", "complex_paper_fixed"])
def test_boxes_stand_on_shelves_without_intersecting(recipe):
    r = load_recipe(recipe)
    n_stacked = 0
    for index in range(25):
        scene = sample_scene(r, 7, index)
        for si, sh in enumerate(scene.shelves):
            boxes = [scene.objects[i].layout_box for i in sh.items]
            for b in boxes:
                x0, x1 = b.x_range()
                y0, y1 = b.y_range()
                assert -scene.rack_length / 2 <= x0 and x1 <= scene.rack_length / 2, "box overhangs the board (x)"
                assert -scene.rack_depth / 2 <= y0 and y1 <= scene.rack_depth / 2, "box overhangs the board (y)"
                assert b.z0 + b.sz <= sh.max_item_top + 1e-9, "box reaches into the shelf above"
                if b.z0 > 0:  # stacked: stands on a box whose top is at z0 and which holds its centre
                    supports = [s for s in boxes if abs(s.z0 + s.sz - b.z0) < 1e-9 and
                                s.corners_xy()[:, 0].min() <= b.cx <= s.corners_xy()[:, 0].max()]
                    assert supports, f"floating box on shelf {si} of scene {index}"
                    n_stacked += 1
            for a_i in range(len(boxes)):
                for b_i in range(a_i + 1, len(boxes)):
                    a, b = boxes[a_i], boxes[b_i]
                    z_overlap = min(a.z0 + a.sz, b.z0 + b.sz) - max(a.z0, b.z0) > 1e-9
                    assert not (z_overlap and _footprints_overlap(a, b)), f"boxes intersect in scene {index}"
            # world geometry = shelf frame + board top
            for i in sh.items:
                o = scene.objects[i]
                b = o.layout_box
                assert np.allclose(o.center, (b.cx, b.cy, sh.board_top + b.z0 + b.sz / 2))
    assert n_stacked > 0


def test_paper_placement_centres_each_item_at_its_category_size_and_front_anchor_sets_back():
    """`complex_paper` (box_anchor centre, no jitter, never turned) puts every item that stands
    on a board on the shelf's depth centre line at its category's nominal footprint, yawed by at
    most 5 degrees; `complex` with `setback: 0` puts every one flush with the board's front edge
    (2 cm margin) when nothing stands behind it, and `complex` itself sets some back."""
    def board_items(recipe, n=12):
        for index in range(n):
            scene = sample_scene(recipe, 5, index)
            for sh in scene.shelves:
                for i in sh.items:
                    if scene.objects[i].layout_box.z0 == 0:
                        yield scene, scene.objects[i]

    items = list(board_items(load_recipe("complex_paper")))
    assert len(items) > 50
    for scene, o in items:
        b, (sx, sy, _) = o.layout_box, CATEGORIES[o.category][1]
        assert b.cy == 0.0 and (b.sx, b.sy) == (sx, sy) and abs(b.yaw) <= math.radians(5) + 1e-12, (o.category, b)
    flush = [(s, o) for s, o in board_items(load_recipe("complex", {"setback": 0.0, "back_row": 0.0}))]
    assert flush and all(abs(o.layout_box.y_range()[0] - (-s.rack_depth / 2 + 0.02)) < 1e-9 for s, o in flush)
    front = [o.layout_box.y_range()[0] + s.rack_depth / 2 for s, o in board_items(load_recipe("complex"))]
    assert max(front) > 0.1


def test_paper_fixed_recipe_holds_rack_size_and_camera_fixed():
    """`complex_paper_fixed` (the authors' generator's fixed rack size and camera): every bay 2.3 m
    long and 0.85 m deep with evenly spaced levels 0.57-0.68 m apart, one 287 px lens, the camera
    level, square on and centred on the rack; `complex_paper` varies all of it."""
    def facts(recipe):
        for index in range(12):
            sc = sample_scene(load_recipe(recipe), 3, index)
            tops = np.array([sh.board_top for sh in sc.shelves])
            centre = -sc.camera.R.T @ sc.camera.t
            yield sc, np.diff(tops), centre

    for sc, gaps, centre in facts("complex_paper_fixed"):
        assert (sc.rack_length, sc.rack_depth) == (2.3, 0.85)
        assert 0.57 <= gaps.min() and gaps.max() <= 0.68 and np.ptp(gaps) < 1e-9
        assert sc.camera.K[0, 0] == 287.0
        assert np.allclose(np.abs(sc.camera.R), np.abs(np.round(sc.camera.R))) and abs(centre[0]) < 1e-9
    varied = list(facts("complex_paper"))
    assert len({sc.rack_length for sc, _, _ in varied}) > 1 and max(abs(c[0]) for _, _, c in varied) > 0.01
    assert not all(np.allclose(np.abs(sc.camera.R), np.abs(np.round(sc.camera.R))) for sc, _, _ in varied)


def test_visible_shelves_rule_and_channels():
    r = load_recipe("complex")
    counts = set()
    for index in range(30):
        scene = sample_scene(r, 0, index)
        assert 1 <= len(scene.visible) <= r.R
        assert scene.visible == list(range(scene.visible[0], scene.visible[0] + len(scene.visible)))
        counts.add(len(scene.visible))
    assert counts == set(range(1, r.R + 1)), counts  # every number of visible shelves occurs


def test_object_annotations_match_instance_mask():
    r = load_recipe("complex")
    scene = sample_scene(r, 0, 2)
    W, H = scene.camera.width, scene.camera.height
    # a synthetic instance map: paint a block for the first target item
    i = scene.shelves[scene.visible[0]].items[0] if scene.shelves[scene.visible[0]].items else None
    inst = np.zeros((H, W), np.uint32)
    if i is not None:
        inst[10:20, 30:50] = i + 1
    anns = object_annotations(scene, inst)
    on_rack = [a for a in anns if a["shelf"] is not None]
    assert len(on_rack) == sum(len(s.items) for s in scene.shelves)
    if i is not None:
        a = next(a for a in anns if a["id"] == i + 1)
        assert a["bbox_visible"] == [30, 10, 50, 20] and a["visible_pixels"] == 200
        assert a["category"] == CATEGORIES[scene.objects[i].category][0]
        assert a["channel"] == 0


def test_clutter_stays_in_corridors_and_out_of_the_view_of_the_rack():
    from racklay.synth.scene import SEM

    r = load_recipe("complex", {"clutter": [8, 12]})
    seen = 0
    for index in range(60):
        s = sample_scene(r, 1, index)
        racks = [o for o in s.objects if o.semantic in (SEM["rack"], SEM["shelf"])]
        rc = cuboid_corners(racks)
        rmin, rmax = rc.min(1), rc.max(1)
        clutter = [o for o in s.objects if o.semantic == SEM["clutter"]]
        cc = cuboid_corners(clutter)
        for a, b in zip(cc.min(1), cc.max(1)):
            seen += 1
            assert not ((a[None] < rmax - 1e-6).all(1) & (b[None] > rmin + 1e-6).all(1)).any(), "clutter inside a rack"
            between = (b[0] > -s.rack_length / 2 and a[0] < s.rack_length / 2 and b[1] < -s.rack_depth / 2
                       and a[1] > s.camera.center[1])
            assert not between, "clutter between the camera and the considered rack"
            assert a[2] >= -1e-9, "clutter below the floor"
    assert seen > 100


def test_pallet_racking_units_stand_on_their_level_with_their_parts_inside():
    """Pallet racking (recipe `pallet`): every load unit (a pallet and its load, one box of the
    layout) stands on its level inside the bay, below the next beam, apart from its neighbours;
    the pallet and the cartons drawn for it lie inside the unit's box, and the unit itself is not
    drawn. Some wire-deck levels hold loose cartons instead. The floor under the first beam is a
    storage level (board top 0) in about half the racks."""
    from racklay.synth.scene import CATEGORY_NAMES, PALLET_HEIGHT, SEM

    r = load_recipe("pallet", {"wire_deck": 0.5})
    floors = units = loose = 0
    for index in range(30):
        scene = sample_scene(r, 5, index)
        assert scene.rack_style == "pallet"
        floors += scene.shelves[0].board_top == 0
        for si, sh in enumerate(scene.shelves):
            boxes = [scene.objects[i].layout_box for i in sh.items]
            if any(scene.objects[i].shape != "none" for i in sh.items):
                # a wire-deck level with cartons / crates straight on it: shelving's rules hold
                assert all(scene.objects[i].shape == "box" and b.z0 + b.sz <= sh.max_item_top + 1e-9
                           for i, b in zip(sh.items, boxes))
                loose += 1
                continue
            for i, b in zip(sh.items, boxes):
                units += 1
                o = scene.objects[i]
                assert o.shape == "none" and CATEGORY_NAMES[o.category].startswith("pallet_")
                assert b.z0 == 0 and PALLET_HEIGHT < b.sz <= sh.max_item_top + 1e-9
                assert -scene.rack_length / 2 <= b.x_range()[0] and b.x_range()[1] <= scene.rack_length / 2
                assert -scene.rack_depth / 2 <= b.y_range()[0] and b.y_range()[1] <= scene.rack_depth / 2
                assert np.allclose(o.center, (b.cx, b.cy, sh.board_top + b.sz / 2))
                parts = [p for p in scene.objects if p.part_of == i]
                assert any(p.semantic == SEM["pallet"] for p in parts) and len(parts) >= 2
                pc = cuboid_corners(parts)
                lo, hi = np.array(o.center) - np.array(o.size) / 2, np.array(o.center) + np.array(o.size) / 2
                assert (pc >= lo - 1e-6).all() and (pc <= hi + 1e-6).all(), "a drawn part sticks out of its unit"
            for a_i in range(len(boxes)):
                for b_i in range(a_i + 1, len(boxes)):
                    assert not _footprints_overlap(boxes[a_i], boxes[b_i]), f"units overlap in scene {index}"
    assert units > 30 and loose > 0 and 5 <= floors <= 25, (units, loose, floors)


def test_recipes_without_pallet_racking_keep_their_scenes():
    """Adding the style knob changed nothing for the recipes that do not use it."""
    r = load_recipe("complex")
    for zero in ({"shelving": 1.0, "pallet": 0.0},
                 {"shelving": 1.0, "pallet": 0.0, "cube": 0.0, "wire": 0.0, "boltless": 0.0}):
        r0 = load_recipe("complex", {"rack_style": zero})
        for index in range(5):
            a, b = sample_scene(r, 4, index), sample_scene(r0, 4, index)
            assert [(o.center, o.size, o.material) for o in a.objects] == [(o.center, o.size, o.material) for o in b.objects]
            assert a.rack_style == "shelving" and not any(o.part_of >= 0 for o in a.objects)


def test_cube_units_keep_each_load_inside_its_cell():
    """Cube units (recipe `cube`): a row of square cells between panels is a shelf; every item
    stands on its row's panel inside one cell (between two upright panels, on the deck, below
    the panel above), so loads of neighbouring cells are at least a panel apart."""
    from racklay.synth.scene import SEM

    r = load_recipe("cube", {"box_density": [1.0, 1.0], "cube_bin": 0.5})
    items = neighbours = 0
    for index in range(20):
        scene = sample_scene(r, 6, index)
        assert scene.rack_style == "cube"
        # the considered unit's upright panels: thin, full-height rack parts centred on y = 0
        panels = sorted((o.center[0] - o.size[0] / 2, o.center[0] + o.size[0] / 2) for o in scene.objects
                        if o.semantic == SEM["rack"] and o.size[0] < 0.05 and abs(o.center[1]) < 1e-9
                        and abs(o.center[0]) < scene.rack_length / 2)
        assert panels[0][0] == pytest.approx(-scene.rack_length / 2) and panels[-1][1] == pytest.approx(scene.rack_length / 2)
        cells = [(a[1], b[0]) for a, b in zip(panels, panels[1:])]
        for sh in scene.shelves:
            assert sh.max_item_top < sh.clear_height
            placed = []
            for i in sh.items:
                b = scene.objects[i].layout_box
                items += 1
                assert b.z0 == 0 and b.sz <= sh.max_item_top + 1e-9
                assert -scene.rack_depth / 2 <= b.y_range()[0] and b.y_range()[1] <= scene.rack_depth / 2
                x0, x1 = b.x_range()
                cell = [k for k, (a, c) in enumerate(cells) if a - 1e-9 <= x0 and x1 <= c + 1e-9]
                assert len(cell) == 1, f"scene {index}: an item crosses a panel"
                placed.append((cell[0], x0, x1))
            placed.sort()
            for (ka, _, a1), (kb, b0, _) in zip(placed, placed[1:]):
                if ka != kb:
                    neighbours += 1
                    assert b0 - a1 >= min(p[1] - p[0] for p in panels) - 1e-9
    assert items > 100 and neighbours > 30, (items, neighbours)


def _loads_stand_on_their_deck(scene, sh) -> int:
    """Every load of shelf `sh` of the considered bay stands on its deck or on another load, below
    the shelf's highest item top and inside the deck's length and depth; returns how many."""
    half, hd = scene.rack_length / 2, scene.rack_depth / 2
    for i in sh.items:
        b = scene.objects[i].layout_box
        assert b.z0 >= 0 and b.z0 + b.sz <= sh.max_item_top + 1e-9
        assert -half - 1e-9 <= b.x_range()[0] and b.x_range()[1] <= half + 1e-9
        assert -hd - 1e-9 <= b.y_range()[0] and b.y_range()[1] <= hd + 1e-9
    return len(sh.items)


def test_wire_shelving_loads_stand_on_their_deck_between_the_posts():
    """Wire shelving (recipe `wire`): four round posts outside the decks' corners; every deck is a
    shelf whose wires' tops are the board top; every load stands on its deck (or on another),
    inside its length and depth, and below the next deck's frame."""
    from racklay.synth.scene import SEM, WIRE_POST, WIRE_TRUSS

    r = load_recipe("wire", {"box_density": [1.0, 1.0]})
    items = 0
    for index in range(12):
        scene = sample_scene(r, 7, index)
        assert scene.rack_style == "wire"
        half = scene.rack_length / 2
        posts = [o for o in scene.objects if o.shape == "cylinder" and o.semantic == SEM["rack"]
                 and abs(o.center[1]) < scene.rack_depth / 2 and abs(o.center[0]) < half + WIRE_POST]
        assert len(posts) == 4 and all(abs(o.center[0]) - o.size[0] / 2 == pytest.approx(half) for o in posts)
        for si, sh in enumerate(scene.shelves):
            wires = [o for o in scene.objects if o.semantic == SEM["shelf"] and o.material == "chrome"
                     and abs(o.center[2] + o.size[2] / 2 - sh.board_top) < 1e-9]
            assert len(wires) > 10, "the considered unit's decks are drawn wire by wire"
            if si < len(scene.shelves) - 1:
                assert sh.max_item_top <= sh.clear_height - WIRE_TRUSS
            items += _loads_stand_on_their_deck(scene, sh)
    assert items > 50, items


def test_boltless_decks_are_framed_by_beams_and_carry_their_loads():
    """Boltless shelving (recipe `boltless`): an angle post at each corner of the considered bay,
    a beam on every side of each level rising BOLTLESS_LIP above its deck top, the deck (shelf)
    inside them; every load stands on its deck (or on another), inside the deck, and below the
    next level's beams."""
    from racklay.synth.scene import BOLTLESS_ANGLE, BOLTLESS_LIP, BOLTLESS_PLATE, SEM

    r = load_recipe("boltless", {"box_density": [1.0, 1.0]})
    items = steel = 0
    for index in range(12):
        scene = sample_scene(r, 8, index)
        assert scene.rack_style == "boltless"
        half, hd = scene.rack_length / 2, scene.rack_depth / 2
        flanges = [o for o in scene.objects if o.semantic == SEM["rack"] and o.material == "steel"
                   and half <= abs(o.center[0]) <= half + BOLTLESS_ANGLE and abs(o.center[1]) < hd]
        assert len(flanges) == 8, "two flanges of an angle post at each of the bay's four corners"
        for si, sh in enumerate(scene.shelves):
            decks = [o for o in scene.objects if o.semantic == SEM["shelf"] and abs(o.center[0]) < 1e-9
                     and abs(o.center[1]) < 1e-9 and abs(o.center[2] + o.size[2] / 2 - sh.board_top) < 1e-9]
            assert len(decks) == 1 and decks[0].size[0] == pytest.approx(scene.rack_length)
            steel += decks[0].material == "paint"
            beams = [o for o in scene.objects if o.material == "beam" and abs(o.center[0]) <= half + BOLTLESS_PLATE
                     and abs(o.center[1]) <= hd and abs(o.center[2] + o.size[2] / 2 - sh.board_top - BOLTLESS_LIP) < 1e-9]
            assert len(beams) == 4, "front, back and two side beams frame every deck"
            nxt = scene.shelves[si + 1].board_top if si + 1 < len(scene.shelves) else np.inf
            assert sh.board_top + sh.max_item_top <= nxt + BOLTLESS_LIP - beams[0].size[2]
            items += _loads_stand_on_their_deck(scene, sh)
    assert items > 50 and 0 < steel < sum(len(sample_scene(r, 8, i).shelves) for i in range(12)), (items, steel)


def test_slotted_angle_decks_hang_their_lips_below_and_carry_their_loads():
    """Slotted-angle shelving (recipe `slotted`): a slotted angle post (two flanges) at each corner
    of the considered bay; every level a deck (shelf) whose top is the board top, with lips or
    frame flanges (rack) hanging below it at the front and back and nothing rising above it;
    every load stands on its deck (or on another), inside it, and below the next deck's lips."""
    from racklay.synth.scene import BOLTLESS_ANGLE, SEM

    r = load_recipe("slotted", {"box_density": [1.0, 1.0]})
    items = steel = 0
    for index in range(12):
        scene = sample_scene(r, 8, index)
        assert scene.rack_style == "slotted"
        half, hd = scene.rack_length / 2, scene.rack_depth / 2
        flanges = [o for o in scene.objects if o.material == "slotted" and half <= abs(o.center[0]) <= half + BOLTLESS_ANGLE
                   and abs(o.center[1]) < hd]
        assert len(flanges) == 8 and all(o.semantic == SEM["rack"] for o in flanges)
        for si, sh in enumerate(scene.shelves):
            decks = [o for o in scene.objects if o.semantic == SEM["shelf"] and abs(o.center[0]) < 1e-9
                     and abs(o.center[1]) < 1e-9 and abs(o.center[2] + o.size[2] / 2 - sh.board_top) < 1e-9]
            assert len(decks) == 1 and decks[0].size[:2] == pytest.approx((scene.rack_length, scene.rack_depth))
            steel += decks[0].material == "paint"
            under = [o for o in scene.objects if o.semantic == SEM["rack"] and o.size[0] == pytest.approx(scene.rack_length)
                     and abs(o.center[0]) < 1e-9 and abs(abs(o.center[1]) + o.size[1] / 2 - hd) < 1e-9
                     and abs(o.center[2] + o.size[2] / 2 - (sh.board_top - decks[0].size[2])) < 1e-9]
            assert len(under) == 2, "a lip (or frame flange) under the deck's front and back edges"
            assert not any(o.semantic == SEM["rack"] and abs(o.center[0]) < half and abs(o.center[1]) < hd
                           and sh.board_top < o.center[2] - o.size[2] / 2 < sh.board_top + 0.05 for o in scene.objects)
            if si + 1 < len(scene.shelves):
                nxt = scene.shelves[si + 1].board_top
                assert sh.board_top + sh.max_item_top <= nxt - decks[0].size[2] - under[0].size[2]
            items += _loads_stand_on_their_deck(scene, sh)
    assert items > 50 and 0 < steel < sum(len(sample_scene(r, 8, i).shelves) for i in range(12)), (items, steel)


def test_flush_shelving_items_form_walls_and_overhanging_loads_stay_in_their_bay():
    """`flush_fraction` 1: every item on a shelving board stands flush against its neighbour (a wall
    of cartons: one run in the layouts, as the labelled stock-room photos show); the default keeps
    `min_gap` or more between them. `pallet_overhang`: loads wider than their pallet, the pallet
    drawn under them at its own width, never past the beams' ends nor into a neighbour."""
    from racklay.synth.scene import PALLET_FOOTPRINTS, SEM

    def gaps(recipe):
        out = []
        for index in range(10):
            scene = sample_scene(recipe, 4, index)
            for sh in scene.shelves:
                xs = sorted(scene.objects[i].layout_box.x_range() for i in sh.items
                            if scene.objects[i].layout_box.z0 == 0)           # what stands on the board
                out += [b0 - a1 for (_, a1), (b0, _) in zip(xs, xs[1:])]
        return out

    dense = {"box_density": [1.0, 1.0], "yaw_max_deg": 0.0, "back_row": 0.0}
    walls = gaps(load_recipe("complex", {**dense, "flush_fraction": 1.0}))
    spaced = gaps(load_recipe("complex", dense))
    assert len(walls) > 20 and max(abs(g) for g in walls) < 1e-9, walls
    assert min(spaced) >= 0.03 - 1e-9

    over = load_recipe("pallet", {"pallet_overhang": [0.15, 0.15], "box_density": [1.0, 1.0], "wire_deck": 0.0,
                                  "pallet_packing": 1.0, "pallet_gap": [0.0, 0.4]})
    plain = load_recipe("pallet", {"box_density": [1.0, 1.0], "wire_deck": 0.0, "pallet_packing": 1.0,
                                   "pallet_gap": [0.0, 0.4]})
    widths, wider = [], 0
    pallet_widths = {w for fp in PALLET_FOOTPRINTS for w in fp}
    for index in range(12):
        scene = sample_scene(over, 3, index)
        for sh in scene.shelves:
            xs = sorted(scene.objects[i].layout_box.x_range() for i in sh.items)
            assert all(-scene.rack_length / 2 - 1e-9 <= a and b <= scene.rack_length / 2 + 1e-9 for a, b in xs)
            assert all(a1 <= b0 + 1e-9 for (_, a1), (b0, _) in zip(xs, xs[1:]))           # no overlap
            for i in sh.items:
                unit = scene.objects[i]
                pallet = [o for o in scene.objects if o.part_of == i and o.semantic == SEM["pallet"]][0]
                widths.append(unit.layout_box.sx)
                wider += unit.layout_box.sx > pallet.size[0] + 1e-6
                assert min(abs(pallet.size[0] - w) for w in pallet_widths) < 0.03, pallet.size  # a real pallet
    assert wider > 10 and max(widths) > max(pallet_widths) + 0.1, (wider, max(widths))
    plain_widths = [sample_scene(plain, 3, i).objects[j].layout_box.sx for i in range(12)
                    for sh in sample_scene(plain, 3, i).shelves for j in sh.items]
    assert max(plain_widths) <= max(pallet_widths) + 1e-9


def test_wide_loads_stand_on_two_real_pallets_inside_their_bay():
    """`pallet_wide_fraction`: some loads stand on two pallets (1.6-2.5 m along the beams, as the
    crates, appliance cartons and board stacks of the labelled photos 16, 43 and 45): each is one
    unit, one box in the layouts, with two pallets of real sizes under it within its width; units
    never overlap nor leave the beams, with or without overhangs."""
    from racklay.synth.scene import PALLET_FOOTPRINTS, SEM

    pallet_widths = {w for fp in PALLET_FOOTPRINTS for w in fp}
    dense = {"box_density": [1.0, 1.0], "wire_deck": 0.0, "pallet_wide_fraction": 0.7}
    for keys in ({}, {"pallet_packing": 1.0, "pallet_gap": [0.0, 0.1], "pallet_overhang": [0.0, 0.2]}):
        r = load_recipe("pallet", {**dense, **keys})
        wide = 0
        for index in range(12):
            scene = sample_scene(r, 5, index)
            for sh in scene.shelves:
                xs = sorted(scene.objects[i].layout_box.x_range() for i in sh.items)
                assert all(-scene.rack_length / 2 - 1e-9 <= a and b <= scene.rack_length / 2 + 1e-9 for a, b in xs)
                assert all(a1 <= b0 + 1e-9 for (_, a1), (b0, _) in zip(xs, xs[1:])), xs
                for i in sh.items:
                    unit = scene.objects[i]
                    pallets = [o for o in scene.objects if o.part_of == i and o.semantic == SEM["pallet"]]
                    assert all(min(abs(p.size[0] - w) for w in pallet_widths) < 0.03 for p in pallets)
                    x0, x1 = unit.layout_box.x_range()
                    assert all(x0 - 1e-9 <= p.center[0] - p.size[0] / 2 and p.center[0] + p.size[0] / 2 <= x1 + 1e-9
                               for p in pallets)
                    if len(pallets) == 2:
                        wide += 1
                        assert 1.6 - 1e-9 <= unit.layout_box.sx <= 2.4 + 0.05 + 0.4 + 1e-9, unit.layout_box.sx
                    else:
                        assert len(pallets) == 1
        assert wide > 10, wide


def test_location_labels_sit_on_the_front_beams_and_stay_out_of_the_layouts():
    """`beam_labels`: a scene that has them carries labels on the front face of every front beam
    (or lip) of the considered bay (pallet racking, shelving, boltless, slotted angle), within its length and
    height; they are rack structure, never annotated objects, and change no layout."""
    from racklay.synth.scene import SEM

    for name in ("pallet", "release", "boltless", "slotted"):
        r = load_recipe(name, {"beam_labels": 1.0})
        for index in range(3):
            scene = sample_scene(r, 9, index)
            half, hd = scene.rack_length / 2, scene.rack_depth / 2
            labels = [o for o in scene.objects if o.material == "beam_label"]
            assert labels and all(o.semantic == SEM["rack"] and o.category < 0 and o.layout_box is None for o in labels)
            beams = [o for o in scene.objects if o.material in ("beam", "paint") and o.semantic == SEM["rack"]
                     and abs(o.center[0]) < 1e-9
                     and o.size[0] == pytest.approx(scene.rack_length) and abs(o.center[1] - o.size[1] / 2 + hd) < 1e-9]
            assert len(beams) == sum(sh.board_top > 0 for sh in scene.shelves), f"{name} {index}: one front beam a level"
            for b in beams:
                on = [o for o in labels if abs(o.center[2] - b.center[2]) < 1e-9 and abs(o.center[0]) < half
                      and abs(o.center[1] + hd) < 0.01]
                assert len(on) == max(1, int(scene.rack_length)), "about one label per metre of beam"
                for o in on:
                    assert -hd - 0.005 < o.center[1] - o.size[1] / 2 and o.center[1] + o.size[1] / 2 <= -hd + 1e-9
                    assert abs(o.center[0]) + o.size[0] / 2 <= half and o.size[2] < b.size[2]
        plain = load_recipe(name, {"beam_labels": 0.0})
        assert not any(o.material == "beam_label" for i in range(3) for o in sample_scene(plain, 9, i).objects)


def test_load_unit_annotation_owns_the_pixels_of_its_parts():
    scene = next(s for s in (sample_scene(load_recipe("pallet"), 5, i) for i in range(20))
                 if s.shelves[s.visible[0]].items)
    unit = scene.shelves[scene.visible[0]].items[0]
    parts = [i for i, o in enumerate(scene.objects) if o.part_of == unit]
    W, H = scene.camera.width, scene.camera.height
    inst = np.zeros((H, W), np.uint32)
    inst[10:20, 30:40] = parts[0] + 1      # the pallet
    inst[0:10, 30:50] = parts[1] + 1       # the load above it
    a = next(a for a in object_annotations(scene, inst) if a["id"] == unit + 1)
    assert a["visible_pixels"] == 300 and a["bbox_visible"] == [30, 0, 50, 20]
    assert a["category"].startswith("pallet_") and a["channel"] == 0
    assert not any(x["id"] == p + 1 for x in object_annotations(scene, inst) for p in parts), "parts are not objects"


def test_packed_pallet_levels_stand_their_loads_a_gap_apart():
    """`pallet_packing`: loads on a packed level stand `pallet_gap` apart (the labelled pallet
    photos' gaps are 3-15 cm; the default spreads one pallet per 1/n of the beam, often 0.3 m+),
    still inside the bay and never overlapping."""
    gap = 0.05
    r = load_recipe("pallet", {"pallet_packing": 1.0, "pallet_gap": [gap, gap], "box_density": [1.0, 1.0],
                               "wire_deck": 0.0})
    spread = load_recipe("pallet", {"box_density": [1.0, 1.0], "wire_deck": 0.0})
    seen, spread_gaps = [], []
    for recipe, out in ((r, seen), (spread, spread_gaps)):
        for index in range(12):
            scene = sample_scene(recipe, 3, index)
            for sh in scene.shelves:
                xs = sorted(scene.objects[i].layout_box.x_range() for i in sh.items)
                assert all(-scene.rack_length / 2 - 1e-9 <= a and b <= scene.rack_length / 2 + 1e-9 for a, b in xs)
                out += [b0 - a1 for (_, a1), (b0, _) in zip(xs, xs[1:])]
    assert len(seen) > 10 and all(0.7 * gap - 1e-9 <= g <= 1.3 * gap + 1e-9 for g in seen), seen
    assert np.median(spread_gaps) > 0.15, np.median(spread_gaps)


def test_bays_sized_for_their_pallets_hold_them_end_to_end():
    """`pallet_bay_fit`: a bay sized for its pallets (as a real rack's beams are specified) holds n
    pallets of one footprint on every level, with one clearance between them and at both beam
    ends, and its beams stay within `pallet_bay_length`; full levels then cover most of the beam,
    as in the labelled photos (most of their levels 80-99 % under loads). Off, recipes keep their
    scenes draw for draw."""
    from racklay.synth.scene import PALLET_FOOTPRINTS, SEM

    full = {"box_density": [1.0, 1.0], "wire_deck": 0.0, "pallet_bay_length": [2.4, 4.6]}
    r = load_recipe("pallet", {**full, "pallet_bay_fit": 1.0})
    pallet_widths = {w for fp in PALLET_FOOTPRINTS for w in fp}
    covers = []
    for index in range(12):
        scene = sample_scene(r, 6, index)
        L_ = scene.rack_length
        assert 2.4 - 1e-9 <= L_ <= 4.6 + 1e-9, L_
        footprints = set()
        for sh in scene.shelves:
            if not sh.items:
                continue
            pallets = sorted((o for i in sh.items for o in scene.objects if o.part_of == i and o.semantic == SEM["pallet"]),
                             key=lambda o: o.center[0])
            along = pallets[0].size[0]
            assert min(abs(along - w) for w in pallet_widths) < 0.03
            footprints.add(round(along, 3))
            n = len(pallets)
            gap = (L_ - n * along) / (n + 1)
            assert 0.06 - 1e-6 <= gap <= 0.15 + 1e-6, (L_, n, along)   # mixed's pallet_gap range
            covers.append(sum(scene.objects[i].layout_box.sx for i in sh.items) / L_)
        assert len(footprints) <= 1, "one footprint for every level of the bay"
    assert len(covers) > 15 and np.median(covers) > 0.85, np.median(covers)

    plain = load_recipe("pallet", full)
    off = load_recipe("pallet", {**full, "pallet_bay_fit": 0.0})
    for index in range(3):
        assert sample_scene(plain, 6, index).rack_length == sample_scene(off, 6, index).rack_length


def test_full_warehouse_knobs_build_loads_up_and_fill_the_other_bays():
    """`pallet_load_height` sets how far a load fills its level's clear height above the pallet;
    `neighbour_fill` loads every bay but the considered one at least that densely (what a gap
    between two loads shows in a full warehouse), leaving the considered bay to `box_density`."""
    from racklay.synth.scene import CATEGORY_NAMES, PALLET_HEIGHT

    tall = load_recipe("pallet", {"pallet_load_height": [0.9, 1.0], "box_density": [1.0, 1.0], "wire_deck": 0.0})
    fills = []
    for index in range(10):
        scene = sample_scene(tall, 2, index)
        for sh in scene.shelves:
            fills += [(scene.objects[i].layout_box.sz - PALLET_HEIGHT) / (sh.max_item_top - PALLET_HEIGHT)
                      for i in sh.items]
    assert len(fills) > 20 and min(fills) >= 0.9 - 1e-9, min(fills)

    def other_loads(fill):
        r = load_recipe("pallet", {"neighbour_fill": fill, "box_density": [0.0, 0.0], "wire_deck": 0.0,
                                   "background": {"wall": 0.0, "busy": 1.0}})
        n = 0
        for index in range(6):
            scene = sample_scene(r, 2, index)
            assert all(not sh.items for sh in scene.shelves), "the considered bay follows box_density"
            n += sum(o.shape == "none" and CATEGORY_NAMES[o.category].startswith("pallet_")
                     for o in scene.objects if o.shelf < 0)
        return n

    assert other_loads(0.0) == 0 and other_loads(1.0) > 50


FRONTAL_W, FRONTAL_H, FRONTAL_F = 470, 280, 400.0


def frontal_camera(x: float, dist: float, k1: float = 0.0):
    """A level camera looking straight at a 0.8 m deep rack's front from `dist` metres, eye at
    1 m, at x along the rack; 470 x 280 pixels, focal length 400 px."""
    from racklay.synth.scene import Camera, rotation_world_to_cam

    W, H, f = FRONTAL_W, FRONTAL_H, FRONTAL_F
    C = np.array([x, -0.4 - dist, 1.0])
    R = rotation_world_to_cam(0.0, 0.0, 0.0)
    return Camera(K=np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]]), R=R, t=-R @ C, width=W, height=H, k1=k1)


def test_a_level_cut_by_the_frame_top_counts_when_its_board_shows_and_the_recipe_says_so():
    """`visible_fraction_board`: a level whose board is in the photo and whose opening the frame's
    top edge cuts counts as visible, as labellers count it (docs/annotate.md); a level whose
    board is below the frame does not, however much of its opening shows; 1.0 (the default)
    leaves the opening rule alone."""
    from racklay.synth.scene import ShelfInfo, visible_shelves

    cam = frontal_camera(0.0, 2.0)                           # 2 m in front of a 0.8 m deep rack, eye at 1 m
    # the frame spans z = 1 -+ 140 / 400 * 2 m = 0.30 ... 1.70 m on the rack's front plane
    shelves = [ShelfInfo(0.0, 0.5, 0.45),    # board below the frame, 40 % of its opening in it
               ShelfInfo(0.5, 0.8, 0.75),    # entirely in the frame
               ShelfInfo(1.3, 1.2, 1.1)]     # board in the frame, 33 % of its opening in it
    assert visible_shelves(cam, 2.0, 0.8, shelves, 0.5, 12.0) == [1]
    assert visible_shelves(cam, 2.0, 0.8, shelves, 0.5, 12.0, board_fraction=1.0) == [1]
    assert visible_shelves(cam, 2.0, 0.8, shelves, 0.5, 12.0, board_fraction=0.15) == [1, 2]
    assert visible_shelves(cam, 2.0, 0.8, shelves, 0.5, 12.0, board_fraction=0.4) == [1]


def test_zoomed_cameras_take_their_focal_length_from_long_focal_px():
    """`long_lens_fraction`: that share of cameras draws its focal length from `long_focal_px`
    (phone zoom), the rest from `focal_px`; at 0 (the default) `long_focal_px` changes nothing."""
    def focals(over):
        r = load_recipe("proxy_real", {**SMALL, "camera_distance": [0.5, 20.0], "background": {"wall": 1.0}, **over})  # room to zoom
        return [float(sample_scene(r, 5, i).camera.K[0, 0]) for i in range(24)]

    plain = focals({})
    assert focals({"long_focal_px": [900.0, 1000.0]}) == plain          # zoom off: same cameras
    zoomed = focals({"long_lens_fraction": 1.0, "long_focal_px": [900.0, 1000.0]})
    assert all(900.0 <= f <= 1000.0 for f in zoomed), zoomed
    assert all(170.0 <= f <= 260.0 for f in plain), plain
    half = focals({"long_lens_fraction": 0.5, "long_focal_px": [900.0, 1000.0]})
    assert 4 <= sum(f >= 900.0 for f in half) <= 20, half


def test_frame_extent_draws_the_bay_as_far_as_the_image_shows_it():
    """`layout_extent: frame`: where the image's left or right edge cuts the bay, the layouts draw
    the part of it in the image, as a labeller draws a photo (corners at the photo's edge); a bay
    the image shows whole, and every scene of a recipe without the key, keep the whole bay."""
    from racklay.synth.scene import frame_height, frame_window

    W, f, cam = FRONTAL_W, FRONTAL_F, frontal_camera

    half = W / 2 / f * 1.5                        # 0.88 m of the rack front either side at 1.5 m
    x0, x1 = frame_window(cam(0.0, 1.5), 4.0, 0.8, 1.0)
    assert x0 == pytest.approx(-half, abs=0.006) and x1 == pytest.approx(half, abs=0.006)
    x0, x1 = frame_window(cam(1.5, 1.5), 4.0, 0.8, 1.0)            # the bay's right end in the image
    assert x0 == pytest.approx(1.5 - half, abs=0.006) and x1 == 2.0
    assert frame_window(cam(0.0, 6.0), 4.0, 0.8, 1.0) is None      # the whole bay in the image
    # the frame's top edge at z = 1 + 140 / 400 * 1.5 = 1.525 m cuts a level from 1.2 m to 2.2 m
    assert frame_height(cam(0.0, 1.5), 0.0, 0.8, 1.2, 1.0) == pytest.approx(0.325, abs=0.003)
    assert frame_height(cam(0.0, 1.5), 0.0, 0.8, 0.6, 0.5) is None                # all of it shown
    # barrel distortion shows a little more, and never the far parts it folds back into the image
    x0, x1 = frame_window(cam(0.0, 0.6, k1=-0.12), 40.0, 0.8, 1.0)
    assert 0.6 * W / 2 / f < x1 < 1.3 * 0.6 * W / 2 / f and x0 == pytest.approx(-x1, abs=0.06)

    r = load_recipe("mixed", {**SMALL, "layout_extent": "frame"})
    g = L.Grid(256, r.extent_m)
    cut = heights = 0
    for i in range(12):
        s = sample_scene(r, 3, i)
        plain = sample_scene(load_recipe("mixed", SMALL), 3, i)
        assert plain.layout_window is None and plain.camera.t.tolist() == s.camera.t.tolist()
        top, front = scene_layouts(s, g, r.R)
        whole = scene_layouts(plain, g, r.R)[1]
        lengths = L.shelf_lengths(front, g)
        for k in range(len(s.visible)):
            drawn = (front[k] > 0).any(axis=1).sum() * g.res        # the level's free space, pad included
            shown = s.layout_heights[k] if s.layout_heights else None
            if shown is None:
                assert drawn == pytest.approx((whole[k] > 0).any(axis=1).sum() * g.res)
            else:
                heights += 1
                clear = s.shelves[s.visible[k]].clear_height
                assert 0 < shown < clear and drawn == pytest.approx(shown + L.FRONT_CLEARANCE_PAD_M, abs=g.res)
        if s.layout_window is None:
            np.testing.assert_array_equal(lengths, L.shelf_lengths(whole, g))
            continue
        cut += 1
        x0, x1 = s.layout_window
        assert -s.rack_length / 2 <= x0 < x1 <= s.rack_length / 2 and x1 - x0 < s.rack_length
        for k in range(len(s.visible)):
            assert lengths[k] == pytest.approx(x1 - x0, abs=2 * g.res)
    assert cut >= 4 and heights >= 3


def test_row_extent_continues_the_shelves_into_the_neighbouring_bays():
    """`layout_extent: row`: the labelling guide draws "the bay (or bays) the photo is about", so
    a level continues across the shared upright into the next bay as far as the image shows it,
    with that bay's loads; the images and every other draw stay those of `bay` and `frame`, and a
    bay with no neighbour in its row is drawn as `frame` draws it."""
    r = load_recipe("mixed", {**SMALL, "layout_extent": "row"})
    frame = load_recipe("mixed", {**SMALL, "layout_extent": "frame"})
    g = L.Grid(256, r.extent_m)
    across = alone = 0
    for i in range(40):
        s, f = sample_scene(r, 5, i), sample_scene(frame, 5, i)
        assert s.camera.t.tolist() == f.camera.t.tolist() and len(s.objects) == len(f.objects)
        top, front = scene_layouts(s, g, r.R)
        if s.layout_row is None:
            alone += 1
            for a, b in zip((top, front), scene_layouts(f, g, r.R)):
                np.testing.assert_array_equal(a, b)
            continue
        a, b = s.layout_row
        x0, x1 = s.layout_window
        assert a <= x0 < x1 <= b and x1 - x0 <= r.extent_m + 1e-9
        assert a < -s.rack_length / 2 or b > s.rack_length / 2          # a neighbour on one side at least
        centre = (x0 + x1) / 2
        for k, si in enumerate(s.visible):
            # one shelf over the whole window, the upright between the bays included
            assert L.shelf_lengths(front, g)[k] == pytest.approx(x1 - x0, abs=2 * g.res)
            board = s.shelves[si].board_top
            for bx in s.row_boxes[si]:
                # every neighbour's box is a load drawn in the scene, standing on the same level
                assert any(abs(o.center[0] - bx.cx) < 1e-9 and abs(o.center[1] - bx.cy) < 1e-9
                           and abs(o.center[2] - (board + bx.z0 + bx.sz / 2)) < 1e-9
                           and np.allclose(o.size, (bx.sx, bx.sy, bx.sz)) for o in s.objects), bx
                lo, hi = max(bx.x_range()[0], x0), min(bx.x_range()[1], x1)
                if hi - lo > 4 * g.res and bx.z0 < 0.02:
                    across += 1     # (partly) inside the window: drawn as box in the front view
                    col = int(g.x_to_col((lo + hi) / 2 - centre))
                    assert (front[k][:, col] == L.BOX).any()
    assert across >= 3 and alone >= 2


@pytest.mark.parametrize("extent", ["bay", "frame", "row"])
def test_level_spans_are_where_the_image_shows_the_shelf_the_layouts_draw(extent):
    """Placement supervision on renders (meta level_spans, as annotate export writes a labelled
    photo's): per layout channel the image x of the drawn shelf's front ends, left first; the
    middle of that front edge is seen between them; where the frame cuts the bay ('frame', 'row')
    the layouts draw it as far as the image shows it, so the span reaches the image's edge there."""
    from racklay.synth.groundtruth import level_spans

    r = load_recipe("mixed", {"layout_extent": extent})
    cut = 0
    for index in range(16):
        scene = sample_scene(r, 2, index)
        spans = level_spans(scene)
        assert len(spans) == len(scene.visible)
        cam, d = scene.camera, scene.rack_depth
        for k, ((shelf, _), sp) in enumerate(zip(scene.layout_inputs(), spans)):
            assert sp is not None and sp[0] < sp[1]
            x0, x1 = scene.layout_window or (-shelf.length / 2, shelf.length / 2)
            z = scene.shelves[scene.visible[k]].board_top + 0.3 * shelf.clear_height
            mid = cam.image_points([[(x0 + x1) / 2, -d / 2, z]])[0][0, 0] / cam.width
            assert sp[0] < mid < sp[1]
            if scene.layout_window is not None:
                cut += 1
                assert min(abs(sp[0]), abs(sp[1] - 1)) < 0.08, (index, sp)   # the image's edge
            else:
                assert extent == "bay" or (sp[0] > -0.02 and sp[1] < 1.02), (index, sp)   # seen whole
    assert extent == "bay" or cut > 0


def _tall_scenes(n_shelves, seed, count, over):
    """Scenes of small racks of `n_shelves` low shelves, cameras up to 12 m away (tall views)."""
    r = load_recipe("complex", {**SMALL, "n_shelves": n_shelves, "shelf_height": [0.25, 0.4],
                                "camera_distance": [0.35, 12.0], **over})
    return r, [sample_scene(r, seed, i) for i in range(count)]


def _shown(r, s):
    """The shelves a scene's camera shows by the recipe's visibility rule (all of them, not only R)."""
    from racklay.synth.scene import visible_shelves

    return visible_shelves(s.camera, s.rack_length, s.rack_depth, s.shelves, r.visible_fraction,
                           r.detection_range_m, r.visible_fraction_board)


def test_a_tall_view_shows_more_levels_than_it_labels_the_lowest_r_of_them(renderer):
    """`tall_view_fraction`: that share of cameras frames more levels than R (a tall rack
    photographed whole) and the lowest R visible levels get the layout channels, as the labelling
    guide labels photo 17 (docs/annotate.md); the loads of the levels above are in the image with
    no channel. At 0 (the default) no camera shows more than R levels."""
    _, ren = renderer

    def scenes(over):
        return _tall_scenes([7, 9], 3, 16, over)

    r, plain = scenes({})
    assert all(len(_shown(r, s)) <= r.R and s.visible == _shown(r, s) for s in plain)
    r, tall = scenes({"tall_view_fraction": 1.0})
    more = [s for s in tall if len(_shown(r, s)) > r.R]
    assert len(more) >= 12, [len(_shown(r, s)) for s in tall]
    assert all(s.visible == _shown(r, s)[:r.R] for s in tall)       # the lowest R of those in view
    s = more[0]
    top, front = scene_layouts(s, L.Grid(128, r.extent_m), r.R)
    assert top.shape[0] == front.shape[0] == r.R and (front[r.R - 1] > 0).any()
    anns = object_annotations(s, ren.render(s).instance)
    above = set(_shown(r, s)[r.R:])
    up = [a for a in anns if a["shelf"] in above]
    assert up and all(a["channel"] is None for a in up) and any(a["visible_pixels"] > 0 for a in up)
    on = [a for a in anns if a["shelf"] in s.visible]
    assert on and all(a["channel"] == s.visible.index(a["shelf"]) for a in on)   # channel 0: the lowest


def test_tall_view_shelves_draws_tall_racks_for_tall_views_and_leaves_the_others_alone():
    """`tall_view_shelves`: the tall view is decided with the rack, so a recipe can photograph
    a few tall racks whole (here 8-10 shelves) while every other rack keeps `n_shelves` and a
    camera showing at most R of its levels; without `tall_view_fraction` it changes nothing."""
    def scenes(over):
        return _tall_scenes([2, 4], 5, 24, over)

    r, tall = scenes({"tall_view_fraction": 0.5, "tall_view_shelves": [8, 10]})
    counts = [len(s.shelves) for s in tall]
    big = [s for s in tall if len(s.shelves) > 4]
    assert set(counts) <= {2, 3, 4, 8, 9, 10} and 4 <= len(big) <= 20, counts
    assert all(len(_shown(r, s)) <= r.R for s in tall if len(s.shelves) <= 4)
    assert sum(len(_shown(r, s)) > r.R for s in big) >= len(big) // 2
    assert all(s.visible == _shown(r, s)[:r.R] for s in tall)
    with pytest.raises(RecipeError, match="tall_view_shelves.*more than R = 4"):
        load_recipe("complex", {"tall_view_shelves": [3, 10]})
    # without tall views the key draws nothing: the recipe's scenes stay as they were
    _, plain = scenes({})
    _, idle = scenes({"tall_view_shelves": [8, 10]})
    assert [s.camera.t.tolist() for s in plain] == [s.camera.t.tolist() for s in idle]
