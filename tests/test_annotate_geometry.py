"""annotate.geometry against ground truth: a synthetic rack seen by a pinhole camera with known
K and [R|t]. The true rack corners, shelf edges and box front faces are projected into pixels,
fed to the geometry as clicks would be, and the resulting layouts are compared with
racklay.layout's rasterisation of the true scene."""
import numpy as np
import pytest

from annotate import geometry as G
from annotate import schema as S
from racklay import layout as L

W, H, DEPTH = 2.0, 2.0, 0.6
BOARDS = [0.10, 0.75, 1.40]  # board top heights, bottom-up
# (shelf, x0, x1, z0 above board, z1 above board, front offset, depth)
BOXES = [
    (0, 0.10, 0.55, 0.0, 0.40, 0.0, 0.45),
    (0, 0.70, 1.30, 0.0, 0.30, 0.0, 0.60),
    (0, 1.30, 1.70, 0.30, 0.50, 0.0, 0.35),  # resting on something 30 cm up
    (1, 0.20, 0.90, 0.0, 0.50, 0.0, 0.50),
    (1, 1.20, 1.90, 0.0, 0.35, 0.05, 0.40),  # set back 5 cm: a little parallax
    (2, 0.50, 1.50, 0.0, 0.45, 0.0, 0.55),
]
GRID = L.Grid(256, 4.0)


def look_at(C, target):
    f = np.asarray(target, float) - C
    f /= np.linalg.norm(f)
    r = np.cross(f, [0, 0, 1.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    return np.stack([r, d, f])


class Camera:
    def __init__(self, C, target, f=520.0, size=(640, 480)):
        self.C = np.asarray(C, float)
        self.R = look_at(self.C, target)
        self.K = np.array([[f, 0, size[0] / 2], [0, f, size[1] / 2], [0, 0, 1]])

    def project(self, P):
        """World (X right along the rack from its left edge, Y depth away, Z up) -> pixels."""
        P = np.atleast_2d(np.asarray(P, float))
        pc = (P - self.C) @ self.R.T
        assert np.all(pc[:, 2] > 0)
        uv = pc @ self.K.T
        return uv[:, :2] / uv[:, 2:3]


def true_layouts():
    clear = [BOARDS[1] - BOARDS[0], BOARDS[2] - BOARDS[1], H - BOARDS[2]]
    per = []
    for i, c in enumerate(clear):
        boxes = [L.Box(cx=(x0 + x1) / 2 - W / 2, cy=-DEPTH / 2 + o + d / 2, sx=x1 - x0, sy=d, sz=z1 - z0, z0=z0)
                 for s, x0, x1, z0, z1, o, d in BOXES if s == i]
        per.append(L.rasterize_shelf(L.Shelf(W, DEPTH, c), boxes, GRID))
    return L.stack_shelves(per, 4, GRID)


def clicks(cam):
    ann = S.new_annotation("x.png", 640, 480)
    corners = cam.project([[0, 0, H], [W, 0, H], [W, 0, 0], [0, 0, 0]])
    ann["rack"] = {"corners": corners[[2, 0, 3, 1]].tolist(), "width": W, "height": H, "depth": DEPTH, "preset": None}
    # one click somewhere along each board's front edge, given top-down to check the ordering
    for k, z in enumerate(reversed(BOARDS)):
        ann["shelves"].append({"id": k, "point": cam.project([[0.3 + 0.5 * k, 0, z]])[0].tolist()})
    for k, (s, x0, x1, z0, z1, o, d) in enumerate(BOXES):
        zb = BOARDS[s]
        p = cam.project([[x0, o, zb + z0], [x1, o, zb + z1]])  # bottom-left and top-right of its front face
        ann["boxes"].append({"id": k, "p0": p[0].tolist(), "p1": p[1].tolist(), "depth": d, "front_offset": o,
                             **({"on_board": False} if z0 > 0 else {})})
    S.validate_annotation(ann)
    return ann


def iou(a, b):
    u = np.logical_or(a, b).sum()
    return np.logical_and(a, b).sum() / u if u else 1.0


SETTINGS = dict(S.default_settings(), R=4, D=256, extent=4.0)


@pytest.mark.parametrize("cam", [
    Camera([1.0, -3.2, 1.0], [1.0, 0, 1.0]),  # frontal
    Camera([-1.2, -2.4, 1.6], [1.0, 0.0, 0.9]),  # oblique: ~40 degrees from the left, from above
    Camera([3.4, -2.0, 0.4], [1.0, 0.0, 1.1]),  # oblique from the right, from below
], ids=["frontal", "oblique-left", "oblique-right-low"])
def test_layouts_match_ground_truth(cam):
    ann = clicks(cam)
    scene = G.build_scene(ann, SETTINGS)
    assert not scene.warnings
    np.testing.assert_allclose(scene.shelf_v, BOARDS, atol=1e-6)
    assert [b.shelf for b in scene.boxes] == [b[0] for b in BOXES]
    top, front = scene.layouts(4, GRID)
    ttop, tfront = true_layouts()
    for i in range(3):
        for view, a, b in (("top", top, ttop), ("front", front, tfront)):
            for cls in (L.SHELF, L.BOX):
                m = iou(a[i] == cls, b[i] == cls)
                assert m >= 0.9, f"shelf {i} {view} class {cls}: IoU {m:.3f}"
    assert not top[3].any() and not front[3].any()


def test_exact_when_fronts_on_plane():
    """With every front face in the rack plane the mapping is exact (up to pixel rounding)."""
    cam = Camera([-1.2, -2.4, 1.6], [1.0, 0.0, 0.9])
    ann = clicks(cam)
    scene = G.build_scene(ann, SETTINGS)
    b = scene.boxes[0]
    assert b.u0 == pytest.approx(0.10, abs=1e-6) and b.u1 == pytest.approx(0.55, abs=1e-6)
    assert b.v1 - b.v0 == pytest.approx(0.40, abs=1e-6)
    assert scene.boxes[2].z0 == pytest.approx(0.30, abs=1e-6)


def test_back_projection_round_trip():
    cam = Camera([3.4, -2.0, 0.4], [1.0, 0.0, 1.1])
    ann = clicks(cam)
    scene = G.build_scene(ann, SETTINGS)
    out = G.box_outline(scene.plane, scene.boxes[3])
    s, x0, x1, z0, z1, _, _ = BOXES[3]
    want = cam.project([[x0, 0, BOARDS[s] + z0], [x1, 0, BOARDS[s] + z0], [x1, 0, BOARDS[s] + z1], [x0, 0, BOARDS[s] + z1]])
    np.testing.assert_allclose(out, want, atol=1e-6)
    line = G.shelf_line(scene.plane, BOARDS[1])
    np.testing.assert_allclose(line, cam.project([[0, 0, BOARDS[1]], [W, 0, BOARDS[1]]]), atol=1e-6)


@pytest.mark.parametrize("cam", [Camera([1.0, -3.2, 1.0], [1.0, 0, 1.0]), Camera([3.4, -2.0, 0.4], [1.0, 0.0, 1.1])],
                         ids=["frontal", "oblique-right-low"])
def test_level_spans_are_the_racks_ends_in_the_photo(cam):
    """Each level's span (what placement supervision trains on) is where the camera sees the
    rack's left and right ends at 30 % of the level's clear height, in image widths; from below and
    to the side the rack is a trapezoid, so the levels' spans differ."""
    scene = G.build_scene(clicks(cam), SETTINGS)
    spans = np.array(scene.level_spans(640))
    clear = [BOARDS[1] - BOARDS[0], BOARDS[2] - BOARDS[1], H - BOARDS[2]]
    want = [np.sort(cam.project([[0, 0, b + 0.3 * c], [W, 0, b + 0.3 * c]])[:, 0]) / 640 for b, c in zip(BOARDS, clear)]
    np.testing.assert_allclose(spans, want, atol=1e-6)
    assert (spans[:, 0] < spans[:, 1]).all()


def test_front_components_to_proposals_round_trip():
    """Predicted layouts = the true ones -> proposals whose rectangles match the true boxes."""
    cam = Camera([1.0, -3.2, 1.0], [1.0, 0, 1.0])
    ann = clicks(cam)
    scene = G.build_scene(ann, SETTINGS)
    top, front = true_layouts()
    props = G.front_box_rects(front, top, GRID, scene.shelf_v, W, DEPTH)
    # every true box comes back as its own component (box 2 only touches box 1 diagonally)
    got = sorted((p.shelf, p.u0, p.u1) for p in props)
    want = sorted((s, x0, x1) for s, x0, x1, *_ in BOXES)
    assert [g[0] for g in got] == [w[0] for w in want]
    np.testing.assert_allclose([g[1:] for g in got], [w[1:] for w in want], atol=GRID.res)
    p = [p for p in props if p.shelf == 2][0]
    assert p.v0 == pytest.approx(BOARDS[2], abs=0.02) and p.v1 == pytest.approx(BOARDS[2] + 0.45, abs=0.02)
    assert p.depth == pytest.approx(0.55, abs=0.02) and p.front_offset == pytest.approx(0, abs=0.02)
    box = G.proposal_to_box(scene.plane, p, 99)
    mb = G.metric_box(scene.plane, box, scene.shelf_v, DEPTH, DEPTH)
    assert mb.shelf == 2 and mb.u0 == pytest.approx(p.u0, abs=1e-3)


def test_bad_corners_refused():
    with pytest.raises(G.GeometryError, match="4 rack corners"):
        G.RackPlane.from_corners([[0, 0], [1, 1], [2, 2]], 2, 2)
    with pytest.raises(G.GeometryError, match="one line"):
        G.RackPlane.from_corners([[0, 0], [10, 10], [20, 20], [30, 30]], 2, 2)


def test_too_many_shelves_for_R():
    cam = Camera([1.0, -3.2, 1.0], [1.0, 0, 1.0])
    ann = clicks(cam)
    scene = G.build_scene(ann, SETTINGS)
    with pytest.raises(G.GeometryError, match="R=2"):
        scene.layouts(2, GRID)


def test_proposals_clipped_below_next_board():
    front = np.zeros((4, GRID.size, GRID.size), np.uint8)
    L.fill_axis_rect(front[0], GRID, -0.5, 0.5, 0.0, 1.5, L.BOX)  # a 1.5 m "box" on a 0.65 m shelf
    props = G.front_box_rects(front, None, GRID, [0.1], W, DEPTH, tops=[0.75])
    assert len(props) == 1 and props[0].v1 == pytest.approx(0.75) and props[0].v0 == pytest.approx(0.1)


def test_touching_stacks_are_proposed_one_by_one():
    """A wall of cartons (two stacks touching, different heights) is two proposals, not one band."""
    shelf = L.Shelf(W, DEPTH, 0.6)
    lay = L.rasterize_shelf(shelf, [L.Box(-0.4, 0.0, 0.6, 0.4, 0.25), L.Box(0.2, 0.0, 0.6, 0.4, 0.5)], GRID)
    top, front = (np.stack([v] + [np.zeros_like(v)] * 3) for v in (lay.top, lay.front))
    props = sorted(G.front_box_rects(front, top, GRID, [0.1], W, DEPTH), key=lambda p: p.u0)
    assert len(props) == 2
    np.testing.assert_allclose([(p.u0, p.u1) for p in props], [(W / 2 - 0.7, W / 2 - 0.1), (W / 2 - 0.1, W / 2 + 0.5)],
                               atol=GRID.res)
    np.testing.assert_allclose([p.v1 - p.v0 for p in props], [0.25, 0.5], atol=GRID.res)



#: a frontal 2 x 2 m rack filling a 640 x 640 photo: 320 px a metre, u = x / 320, v = 2 - y / 320
FRONTAL = G.RackPlane.from_corners([[0, 0], [640, 0], [640, 640], [0, 640]], 2.0, 2.0)


def _photo_with_slots(*slots, light=200, dark=60):
    """Luminance of that photo: light, with dark stretches (u0, u1) over the whole height."""
    luma = np.full((640, 640), light, np.uint8)
    for u0, u1 in slots:
        luma[:, int(round(u0 * 320)):int(round(u1 * 320))] = dark
    return luma


def test_a_proposal_is_cut_where_the_photo_shows_a_gap():
    """One proposal over two loads with a dark 8 cm slot between them in the photo becomes two,
    the slot left between them; over three loads, three; each keeps its heights, depth and offset."""
    p = G.Proposal(0, 0.30, 1.70, 0.10, 0.60, 0.5, 0.02, 0.9)
    two = G.split_at_dark_gaps(p, _photo_with_slots((0.96, 1.04)), FRONTAL)
    assert len(two) == 2
    np.testing.assert_allclose([(q.u0, q.u1) for q in two], [(0.30, 0.96), (1.04, 1.70)], atol=0.011)
    assert all((q.shelf, q.v0, q.v1, q.depth, q.front_offset, q.score) == (0, 0.10, 0.60, 0.5, 0.02, 0.9) for q in two)
    three = G.split_at_dark_gaps(p, _photo_with_slots((0.75, 0.80), (1.20, 1.30)), FRONTAL)
    np.testing.assert_allclose([(q.u0, q.u1) for q in three], [(0.30, 0.75), (0.80, 1.20), (1.30, 1.70)], atol=0.011)


def test_no_cut_without_a_narrow_deep_slot():
    """A photo that is even along the proposal, a dark stretch wider than close_m (a dark load, not
    a gap), a slot too shallow, one closer than min_part_m to an end, a proposal too narrow to
    halve, and a cut switched off (depth 0): the proposal stays as it is."""
    p = G.Proposal(0, 0.30, 1.70, 0.10, 0.60, None, 0.0)
    for luma, cfg in [(_photo_with_slots(), None), (_photo_with_slots((0.8, 1.3)), None),
                      (_photo_with_slots((0.96, 1.04), dark=170), None), (_photo_with_slots((0.35, 0.42)), None),
                      (_photo_with_slots((0.96, 1.04)), G.GapSplit(depth=0))]:
        assert G.split_at_dark_gaps(p, luma, FRONTAL, cfg) == [p]
    narrow = G.Proposal(0, 0.82, 1.18, 0.10, 0.60, None, 0.0)
    assert G.split_at_dark_gaps(narrow, _photo_with_slots((0.96, 1.04)), FRONTAL) == [narrow]
    with pytest.raises(ValueError, match="rows"):
        G.GapSplit(rows=(0.6, 0.2))
    with pytest.raises(ValueError, match="close_m"):
        G.GapSplit(close_m=0)

def _one_box_scene(v0, v1, on_board=None):
    """A frontal 2 x 2 m rack filling a 640 x 640 photo (320 px a metre), boards at 0.1 and 0.75 m."""
    ann = S.new_annotation("x.png", 640, 640)
    ann["rack"].update(corners=[[0, 0], [640, 0], [640, 640], [0, 640]], width=2.0, height=2.0, depth=0.6)
    px = lambda v: 640 - v * 320  # noqa: E731
    ann["shelves"] = [{"id": 0, "point": [100, px(0.10)]}, {"id": 1, "point": [100, px(0.75)]}]
    b = {"id": 0, "p0": [64, px(v0)], "p1": [256, px(v1)]}
    if on_board is not None:
        b["on_board"] = on_board
    ann["boxes"] = [b]
    return G.build_scene(ann, SETTINGS)


def test_box_set_back_stands_on_its_board():
    """A box set back on its shelf looks 8 cm above the board in the photo (before: it floated
    0.07-0.10 m up); it stands on the board unless the labeller says it floats."""
    b = _one_box_scene(0.18, 0.50).boxes[0]
    assert (b.shelf, b.z0, b.v0) == (0, 0.0, pytest.approx(0.10))
    free = _one_box_scene(0.18, 0.50, on_board=False).boxes[0]
    assert free.shelf == 0 and free.z0 == pytest.approx(0.08)



def test_rough_edges_snap_to_the_rack_and_to_an_overlapping_neighbour_but_gaps_stay():
    """Labellers click roughly: a side 3 cm inside the rack's edge moves onto it, two cartons
    drawn 4 cm into each other meet halfway, two cartons 2 cm apart stay apart (a real gap),
    and a carton standing on another keeps its own edges."""
    ann = S.new_annotation("x.png", 640, 640)
    ann["rack"].update(corners=[[0, 0], [640, 0], [640, 640], [0, 640]], width=2.0, height=2.0, depth=0.6)
    px = lambda u, v: [u * 320, 640 - v * 320]  # noqa: E731   frontal: 320 px a metre
    ann["shelves"] = [{"id": 0, "point": px(1.0, 0.10)}, {"id": 1, "point": px(1.0, 0.75)}]
    rows = [(0.03, 0.50, 0.10, 0.40),    # 3 cm from the left edge
            (0.46, 0.90, 0.10, 0.40),    # 4 cm into the first
            (0.92, 1.40, 0.10, 0.40),    # 2 cm gap to the second
            (0.95, 1.35, 0.40, 0.60),    # stacked on the third
            (1.45, 1.97, 0.10, 0.50)]    # 3 cm from the right edge
    ann["boxes"] = [{"id": k, "p0": px(u0, v0), "p1": px(u1, v1), **({"on_board": False} if v0 > 0.2 else {})}
                    for k, (u0, u1, v0, v1) in enumerate(rows)]
    b = G.build_scene(ann, SETTINGS).boxes
    assert b[0].u0 == 0.0 and b[4].u1 == 2.0
    assert b[0].u1 == pytest.approx(0.48) and b[1].u0 == pytest.approx(0.48)
    assert b[1].u1 == pytest.approx(0.90) and b[2].u0 == pytest.approx(0.92)
    assert (b[3].u0, b[3].u1) == (pytest.approx(0.95), pytest.approx(1.35))
