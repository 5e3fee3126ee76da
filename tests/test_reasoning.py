"""Rack reasoning: counts, metric volumes, view fusion, 3D export and `racklay analyze`."""
from __future__ import annotations

import json

import numpy as np
import pytest

from racklay import layout as L
from racklay.data import RackLayRoot
from racklay.export3d import COLORS, glb_bytes, glb_mesh_arrays, ply_text, rack_parts, read_glb, render_figure
from racklay.reasoning import ReasoningConfig, analyze_layouts, analyze_shelf

G = L.Grid(256)  # 3.125 cm pixels; the default opening (4 cm) rounds to 1 px: no-op
RES = G.res
SHELF = L.Shelf(2.0, 0.8, 0.6)


def n_rows(v0, v1, grid=G):
    """Rows whose centre lies in [v0, v1) (top-view y or front-view z)."""
    c = grid.row_centers()
    return int(((c >= v0) & (c < v1)).sum())


def n_cols(x0, x1, grid=G):
    c = grid.centers()
    return int(((c >= x0) & (c < x1)).sum())


def expected_volume(box: L.Box, grid=G) -> float:
    """Exact volume of an axis-aligned box after rasterising: footprint pixels x height rows."""
    x0, x1 = box.x_range()
    y0, y1 = box.y_range()
    return n_cols(x0, x1, grid) * n_rows(y0, y1, grid) * n_rows(box.z0, box.z0 + box.sz, grid) * grid.res ** 3


def expected_capacity(shelf: L.Shelf, grid=G) -> float:
    L_, W, H = shelf.length, shelf.depth, shelf.clear_height
    return (n_cols(-L_ / 2, L_ / 2, grid) * n_rows(-W / 2, W / 2, grid) * grid.res ** 2
            * (n_rows(0.0, H + L.FRONT_CLEARANCE_PAD_M, grid) * grid.res - L.FRONT_CLEARANCE_PAD_M))


def one_shelf(boxes, shelf=SHELF, grid=G, cfg=ReasoningConfig()):
    lay = L.rasterize_shelf(shelf, boxes, grid)
    return analyze_shelf(lay.top, lay.front, grid, cfg), lay


# --- layout span helpers ------------------------------------------------------------------------
def test_grid_span_helpers_invert_fill_axis_rect():
    g = L.Grid(64, 4.0)
    canvas = np.zeros((64, 64), np.uint8)
    L.fill_axis_rect(canvas, g, -0.5, 0.75, 0.25, 1.0, 1)
    rows = np.flatnonzero(canvas.any(axis=1))
    cols = np.flatnonzero(canvas.any(axis=0))
    assert g.col_span_to_x(cols[0], cols[-1] + 1) == (-0.5, 0.75)
    assert g.row_span_to_v(rows[0], rows[-1] + 1) == (0.25, 1.0)
    assert g.px_to_m(8) == pytest.approx(0.5)
    assert g.m_to_px(0.5) == 8 and g.m_to_px(0.001) == 1


# --- exact counts and volumes -------------------------------------------------------------------
def test_separate_boxes_exact_counts_and_volumes():
    boxes = [L.Box(-0.6, 0.0, 0.4, 0.5, 0.3), L.Box(0.0, 0.1, 0.3, 0.4, 0.5), L.Box(0.6, -0.1, 0.25, 0.3, 0.2)]
    s, _ = one_shelf(boxes)
    assert s.complete and len(s.boxes) == 3
    assert s.length_m == pytest.approx(n_cols(-1, 1) * RES)
    assert s.depth_m == pytest.approx(n_rows(-0.4, 0.4) * RES)
    assert s.clear_height_m == pytest.approx(n_rows(0, 0.65) * RES - 0.05)
    assert s.capacity_m3 == pytest.approx(expected_capacity(SHELF), rel=1e-12)
    for got, want in zip(s.boxes, boxes):  # sorted by x
        assert got.volume_m3 == pytest.approx(expected_volume(want), rel=1e-12)
        assert got.x[0] == pytest.approx(want.x_range()[0], abs=RES)
        assert got.y[1] == pytest.approx(want.y_range()[1], abs=RES)
        assert got.z == pytest.approx((0.0, want.sz), abs=RES)
        assert not got.hidden and not got.split
    occupied = sum(expected_volume(b) for b in boxes)
    assert s.free_m3 == pytest.approx(expected_capacity(SHELF) - occupied, rel=1e-12)
    # and the quantised answer is close to the true metric one
    true_free = 2.0 * 0.8 * 0.6 - sum(b.sx * b.sy * b.sz for b in boxes)
    assert abs(s.free_m3 - true_free) / true_free < 0.05


def test_rotated_box_volume_uses_footprint_not_bounding_box():
    box = L.Box(0.0, 0.0, 0.5, 0.3, 0.4, yaw=0.6)
    s, lay = one_shelf([box])
    (b,) = s.boxes
    footprint = (lay.top == L.BOX).sum() * RES ** 2
    assert b.footprint_m2 == pytest.approx(footprint)
    assert b.volume_m3 == pytest.approx(footprint * n_rows(0, 0.4) * RES)
    assert b.volume_m3 < b.size[0] * b.size[1] * b.size[2] * 0.8
    assert b.footprint_m2 == pytest.approx(0.5 * 0.3, rel=0.1)


def test_empty_shelf_is_all_free():
    s, _ = one_shelf([])
    assert s.boxes == [] and s.occupied_m3 == 0
    assert s.free_m3 == pytest.approx(s.capacity_m3) and s.free_fraction == pytest.approx(1.0)


def test_boxes_offset_off_centre_shelf_z_base_from_layout():
    # a box stacked on something (z0 > 0) keeps its z-range
    box = L.Box(0.3, 0.0, 0.3, 0.3, 0.2, z0=0.15)
    s, _ = one_shelf([box])
    (b,) = s.boxes
    assert b.z == pytest.approx((n_rows(0, 0.15) * RES, n_rows(0, 0.35) * RES))


# --- fusion edge cases --------------------------------------------------------------------------
def test_touching_in_front_view_but_not_top_is_split_by_column_occupancy():
    # adjacent in x (one front blob), apart in y (two top blobs), different heights
    a = L.Box(-0.35, -0.2, 0.3, 0.3, 0.3)
    b = L.Box(-0.05, 0.2, 0.3, 0.3, 0.5)
    s, lay = one_shelf([a, b])
    from racklay.reasoning import components
    assert len(components(lay.front == L.BOX, G, 0.01)) == 1
    assert len(s.boxes) == 2
    got = sorted(s.boxes, key=lambda q: q.x[0])
    assert got[0].z[1] == pytest.approx(n_rows(0, 0.3) * RES)
    assert got[1].z[1] == pytest.approx(n_rows(0, 0.5) * RES)
    assert [q.volume_m3 for q in got] == pytest.approx([expected_volume(a), expected_volume(b)])
    assert not any(q.hidden for q in got)


def test_touching_stacks_of_different_heights_are_cut_at_the_step():
    # a wall of cartons: three stacks side by side, touching in both views (one blob in each)
    boxes = [L.Box(-0.6, 0.0, 0.4, 0.5, 0.3), L.Box(-0.2, 0.0, 0.4, 0.5, 0.55), L.Box(0.2, 0.0, 0.4, 0.5, 0.3)]
    s, lay = one_shelf(boxes)
    from racklay.reasoning import components
    assert len(components(lay.top == L.BOX, G, 0.01)) == 1 and len(components(lay.front == L.BOX, G, 0.01)) == 1
    got = sorted(s.boxes, key=lambda q: q.x[0])
    assert len(got) == 3
    for q, b in zip(got, boxes):
        assert q.x == pytest.approx(b.x_range(), abs=RES) and q.z[1] == pytest.approx(b.sz, abs=RES)
    assert s.occupied_m3 == pytest.approx(sum(expected_volume(b) for b in boxes), rel=1e-9)
    # the same wall with splitting off is one stack; steps below split_step_m do not cut
    off, _ = one_shelf(boxes, cfg=ReasoningConfig(split_step_m=0))
    assert len(off.boxes) == 1
    coarse, _ = one_shelf(boxes, cfg=ReasoningConfig(split_step_m=0.3))
    assert len(coarse.boxes) == 1


def test_layout_figure_outlines_each_stack_read(tmp_path):
    from matplotlib.patches import Rectangle

    from racklay.viz import layout_figure

    boxes = [L.Box(-0.6, 0.0, 0.4, 0.5, 0.3), L.Box(-0.2, 0.0, 0.4, 0.5, 0.55), L.Box(0.5, 0.0, 0.3, 0.5, 0.2)]
    lay = L.rasterize_shelf(SHELF, boxes, G)
    top, front = L.stack_shelves([lay], 4, G)
    fig = layout_figure(None, top, front, out=tmp_path / "f.png", grid=G, outline_stacks=True)
    outlines = [[p for p in ax.patches if isinstance(p, Rectangle)] for ax in fig.axes]
    assert [len(o) for o in outlines] == [3, 0, 0, 0, 3, 0, 0, 0]     # shelf 1 top, then front
    x0s = sorted(p.get_x() for p in outlines[4])
    assert x0s == pytest.approx([b.x_range()[0] for b in boxes], abs=RES)
    assert (tmp_path / "f.png").stat().st_size > 0


def test_step_segments_cuts_steps_not_noise():
    from racklay.reasoning import step_segments

    rng = np.random.default_rng(0)
    h = np.r_[np.full(30, 0.30), np.full(20, 0.50)] + rng.normal(0, 0.01, 50)
    assert step_segments(h, 0.08, 4) == [(0, 30), (30, 50)]
    assert step_segments(np.full(50, 0.4) + rng.normal(0, 0.02, 50), 0.08, 4) == [(0, 50)]
    # no piece is narrower than min_len; too short a profile is one piece
    spans = step_segments(np.r_[np.full(30, 0.3), np.full(3, 0.9)], 0.08, 4)
    assert spans[0][0] == 0 and spans[-1][1] == 33 and all(b - a >= 4 for a, b in spans)
    assert step_segments(np.r_[0.1, 0.9], 0.08, 4) == [(0, 2)]


def test_stack_hidden_behind_another_gets_the_front_height():
    front_box = L.Box(0.2, -0.2, 0.4, 0.3, 0.5)   # x in [0, 0.4), near the camera, tall
    behind = L.Box(0.2, 0.2, 0.2, 0.3, 0.2)       # x in [0.1, 0.3): fully hidden in the front view
    s, _ = one_shelf([front_box, behind])
    assert len(s.boxes) == 2
    hid = [b for b in s.boxes if b.hidden]
    vis = [b for b in s.boxes if not b.hidden]
    assert len(hid) == 1 and len(vis) == 1
    assert vis[0].z[1] == pytest.approx(n_rows(0, 0.5) * RES)
    assert hid[0].z[1] == pytest.approx(n_rows(0, 0.5) * RES)  # an upper bound: all the view shows
    assert hid[0].y[0] == pytest.approx(0.05, abs=RES)


def test_partially_hidden_stacks_keep_their_own_heights():
    a = L.Box(0.2, -0.2, 0.4, 0.3, 0.3)  # x [0, 0.4), front, short
    b = L.Box(0.4, 0.2, 0.4, 0.3, 0.5)   # x [0.2, 0.6), behind, tall
    s, _ = one_shelf([a, b])
    got = sorted(s.boxes, key=lambda q: q.x[0])
    assert len(got) == 2 and not any(q.hidden for q in got)
    assert got[0].z[1] == pytest.approx(n_rows(0, 0.3) * RES)
    assert got[1].z[1] == pytest.approx(n_rows(0, 0.5) * RES)


def test_touching_in_top_view_but_not_front_is_split_at_front_gaps():
    a = L.Box(-0.3, 0.0, 0.3, 0.4, 0.3)  # x [-0.45, -0.15)
    b = L.Box(0.05, 0.0, 0.3, 0.4, 0.4)  # x [-0.10, 0.20): a 5 cm gap
    lay = L.rasterize_shelf(SHELF, [a, b], G)
    top = lay.top.copy()
    gap = slice(int(G.x_to_col(-0.16)), int(G.x_to_col(-0.09)) + 1)
    rows = slice(int(G.y_to_row(0.05)), int(G.y_to_row(-0.05)))
    top[rows, gap] = L.BOX  # a predicted bridge joins the two footprints
    from racklay.reasoning import components
    assert len(components(top == L.BOX, G, 0.01)) == 1
    s = analyze_shelf(top, lay.front, G)
    assert len(s.boxes) == 2 and all(q.split for q in s.boxes)
    got = sorted(s.boxes, key=lambda q: q.x[0])
    assert [q.volume_m3 for q in got] == pytest.approx([expected_volume(a), expected_volume(b)])


def test_top_footprint_touching_two_front_regions_by_slivers_is_kept_whole():
    # a (mis)predicted pair of views: the footprint lies in the front view's gap except for one
    # column at each end; it is neither dropped nor cut into slivers
    top = L.rasterize_shelf(SHELF, [L.Box(0.2, 0.0, 0.4, 0.2, 0.3)], G).top       # x [0, 0.4)
    front = L.rasterize_shelf(SHELF, [L.Box(-0.085, 0, 0.23, 0.3, 0.3),            # x [-0.2, 0.03)
                                      L.Box(0.485, 0, 0.23, 0.3, 0.3)], G).front   # x [0.37, 0.6)
    s = analyze_shelf(top, front, G)
    assert len(s.boxes) == 1 and not s.boxes[0].split
    assert s.unmatched_front == 1 and s.unmatched_top == 0


def test_noise_blobs_below_min_size_are_ignored_and_unmatched_blobs_not_counted():
    box = L.Box(-0.5, 0.0, 0.3, 0.3, 0.3)
    lay = L.rasterize_shelf(SHELF, [box], G)
    top, front = lay.top.copy(), lay.front.copy()
    c = int(G.x_to_col(0.5))
    top[128, c:c + 2] = L.BOX          # 2 px: 0.002 m^2
    front[120, c:c + 3] = L.BOX        # 3 px in the free space
    s = analyze_shelf(top, front, G)
    assert len(s.boxes) == 1 and s.unmatched_top == 0 and s.unmatched_front == 0
    # a front-view box big enough to be real but with nothing in the top view: reported, not counted
    z0 = int(G.z_to_row(0.3))
    front[z0:z0 + 6, c:c + 6] = L.BOX
    s = analyze_shelf(top, front, G)
    assert len(s.boxes) == 1 and s.unmatched_front == 1
    # the opening removes thin spurs when the kernel is wider than a pixel
    top2 = lay.top.copy()
    top2[120:140, c] = L.BOX  # 1-px-wide line, 0.02 m^2
    s = analyze_shelf(top2, lay.front, G, ReasoningConfig(open_m=0.1))
    assert len(s.boxes) == 1


def test_prediction_like_noise_is_cleaned():
    """Salt noise and ragged box tops (what a model's argmax looks like) leave counts intact and
    heights within a pixel."""
    boxes = [L.Box(-0.6, 0.0, 0.4, 0.5, 0.3), L.Box(0.0, 0.1, 0.3, 0.4, 0.5), L.Box(0.6, -0.1, 0.25, 0.3, 0.2)]
    lay = L.rasterize_shelf(SHELF, boxes, G)
    rng = np.random.default_rng(0)
    top, front = lay.top.copy(), lay.front.copy()
    for v in (top, front):
        inside = v == L.SHELF
        salt = inside & (rng.uniform(size=v.shape) < 0.01)
        v[salt] = L.BOX
    # ragged tops: each box column's top pixel randomly removed or one extra added
    for c in np.flatnonzero((front == L.BOX).any(axis=0)):
        r = int(np.argmax(front[:, c] == L.BOX))
        if rng.uniform() < 0.3:
            front[r, c] = L.SHELF
        elif rng.uniform() < 0.3:
            front[r - 1, c] = L.BOX
    # spurs: a shelf-class streak beyond the board's right end, a spike above the free space
    c1 = int(G.x_to_col(1.0))
    top[128:131, c1:c1 + 12] = L.SHELF
    z1 = int(G.z_to_row(0.65))
    front[z1 - 8:z1, 100:104] = L.SHELF
    clean, _ = one_shelf(boxes)
    s = analyze_shelf(top, front, G)
    assert (s.length_m, s.depth_m, s.clear_height_m) == (clean.length_m, clean.depth_m, clean.clear_height_m)
    assert len(s.boxes) == 3 and s.unmatched_top == 0 and s.unmatched_front == 0
    for a, b in zip(s.boxes, clean.boxes):
        assert a.z[1] == pytest.approx(b.z[1], abs=RES)
        assert a.footprint_m2 == pytest.approx(b.footprint_m2, rel=0.05)


# --- racks: missing shelves, incomplete views, report, JSON -------------------------------------
def test_missing_shelves_and_report_line():
    full = L.rasterize_shelf(SHELF, [L.Box(0, 0, 0.3, 0.3, 0.3), L.Box(0.6, 0, 0.3, 0.3, 0.2)], G)
    empty = L.rasterize_shelf(SHELF, [], G)
    top, front = L.stack_shelves([full, None, empty], 4, G)
    r = analyze_layouts(top, front, G)
    assert [s.index for s in r.shelves] == [0, 2]
    assert r.n_shelves == 2 and r.n_box_stacks == 2
    assert r.capacity_m3 == pytest.approx(2 * expected_capacity(SHELF))
    frac = r.free_m3 / r.capacity_m3
    assert r.report() == (f"Rack has 2 shelves, 2 box stacks, and {r.free_m3:.2f} m³ of free space "
                          f"available ({frac * 100:.0f}%)")
    d = json.loads(r.to_json())
    assert d["n_box_stacks"] == 2 and len(d["shelves"]) == 2
    assert d["shelves"][0]["boxes"][0]["size"][2] == pytest.approx(n_rows(0, 0.3) * RES)
    assert d["grid"] == {"D": 256, "extent_m": 8.0, "res_m": RES}

    one = analyze_layouts(*L.stack_shelves([L.rasterize_shelf(SHELF, [L.Box(0, 0, .3, .3, .3)], G)], 4, G), G)
    assert one.report().startswith("Rack has 1 shelf, 1 box stack, and ")

    none = analyze_layouts(np.zeros((4, 256, 256), np.uint8), np.zeros((4, 256, 256), np.uint8), G)
    assert none.n_shelves == 0 and none.free_fraction is None
    assert none.report() == "Rack has 0 shelves, 0 box stacks, and 0.00 m³ of free space available"


def test_shelf_with_one_view_missing_is_flagged_not_summed():
    lay = L.rasterize_shelf(SHELF, [L.Box(0, 0, 0.3, 0.3, 0.3)], G)
    top, front = L.stack_shelves([lay, lay], 4, G)
    front[1] = 0
    r = analyze_layouts(top, front, G)
    assert r.n_shelves == 2 and not r.shelves[1].complete and r.shelves[1].missing_view == "front"
    assert r.capacity_m3 == pytest.approx(r.shelves[0].capacity_m3)
    assert any("no front-view layout" in w for w in r.warnings())
    assert r.report().endswith("[1 shelf seen in one view only: not in the volume]")


def test_bad_layout_arrays_raise_layout_error():
    with pytest.raises(L.LayoutError, match="class ids"):
        analyze_layouts(np.full((4, 32, 32), 7, np.uint8), None, L.Grid(32))
    with pytest.raises(L.LayoutError, match="grid has D=64"):
        analyze_layouts(np.zeros((4, 32, 32), np.uint8), None, L.Grid(64))


# --- 3D export ----------------------------------------------------------------------------------
def _rack():
    lay = L.rasterize_shelf(SHELF, [L.Box(-0.5, 0, 0.3, 0.3, 0.3), L.Box(0.4, 0.1, 0.4, 0.3, 0.45)], G)
    return analyze_layouts(*L.stack_shelves([lay, lay], 4, G), G)


def test_glb_parses_back_with_the_boxes_geometry(tmp_path):
    r = _rack()
    parts = rack_parts(r)
    assert sum(p.kind == "box" for p in parts) == 4 and sum(p.kind == "board" for p in parts) == 2
    data = glb_bytes(parts)
    assert data[:4] == b"glTF" and len(data) % 4 == 0
    doc, binc = read_glb(data)
    assert doc["asset"]["version"] == "2.0"
    assert len(doc["meshes"]) == len(doc["nodes"]) == len(parts)
    assert doc["buffers"][0]["byteLength"] == len(binc)
    # accessors of several meshes share a vertex bufferView: glTF then requires byteStride
    assert [v.get("byteStride") for v in doc["bufferViews"]] == [12, 12, None]
    assert {m["name"] for m in doc["materials"]} == {p.kind for p in parts}
    for i, part in enumerate(parts):
        pos, idx = glb_mesh_arrays(doc, binc, i)
        acc = doc["accessors"][doc["meshes"][i]["primitives"][0]["attributes"]["POSITION"]]
        assert np.allclose(acc["min"], pos.min(0)) and np.allclose(acc["max"], pos.max(0))
        # glTF is y-up: (x, z, -y)
        lo = np.array([part.lo[0], part.lo[2], -part.hi[1]])
        hi = np.array([part.hi[0], part.hi[2], -part.lo[1]])
        assert np.allclose(pos.min(0), lo, atol=1e-6) and np.allclose(pos.max(0), hi, atol=1e-6)
        # every triangle faces outward
        tri = pos[idx.reshape(-1, 3)].astype(np.float64)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        outward = tri.mean(axis=1) - (lo + hi) / 2
        assert (np.einsum("ij,ij->i", normal, outward) > 0).all()
    with pytest.raises(ValueError, match="GLB"):
        read_glb(data[:-4])
    empty_doc, _ = read_glb(glb_bytes([]))
    assert "nodes" not in empty_doc and empty_doc["scenes"] == [{"name": "rack"}]


def test_ply_and_render(tmp_path):
    r = _rack()
    text = ply_text(rack_parts(r))
    head, body = text.split("end_header\n")
    n_v = int(head.split("element vertex ")[1].split()[0])
    n_f = int(head.split("element face ")[1].split()[0])
    lines = body.strip().splitlines()
    assert len(lines) == n_v + n_f and n_v == 8 * 6 and n_f == 6 * 6
    out = tmp_path / "r.png"
    render_figure(r, np.zeros((28, 47, 3), np.uint8), out=out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert set(COLORS) >= {"box", "board", "space", "hidden_box"}


# --- validation against the toy dataset's 3D truth ----------------------------------------------
def test_toy_ground_truth_counts_and_free_volume(tmp_path):
    from racklay.toy import build_toy_dataset

    ds = build_toy_dataset(tmp_path / "toy", n=4, seed=3, D=512)
    for sid in ds.ids():
        meta = ds.read_meta(sid)
        r = analyze_layouts(ds.read_layouts("top", sid), ds.read_layouts("front", sid), L.Grid(512))
        truth = meta["shelves"]
        assert r.n_shelves == len(truth)
        for s, t in zip(r.shelves, truth):
            assert len(s.boxes) == len(t["boxes"])  # >= 3 cm gaps survive at 1.56 cm pixels
            # each metric span is read back as a whole number of pixels: off by < 1 pixel
            dims = [(t["length"], t["depth"], t["clear_height"])] + [(b["sx"], b["sy"], b["sz"]) for b in t["boxes"]]
            tol = [np.prod(np.add(d, 1 / 64)) - np.prod(d) for d in dims]
            cap = np.prod(dims[0])
            occ = sum(np.prod(d) for d in dims[1:])
            assert abs(s.capacity_m3 - cap) < tol[0]
            assert abs(s.free_m3 - (cap - occ)) < sum(tol)
    assert isinstance(ds, RackLayRoot)


# --- command line -------------------------------------------------------------------------------
def test_cli_analyze_layouts_and_malformed_file(tmp_path, capsys):
    from racklay.cli import main
    from racklay.toy import build_toy_dataset

    ds = build_toy_dataset(tmp_path / "toy", n=5, seed=1, D=64)
    ids = ds.split_ids("test") + ds.split_ids("val")
    out = tmp_path / "out"
    assert main(["analyze", "--layouts", str(ds.root), "--split", "test", "--out", str(out), "--format", "both"]) == 0
    printed = capsys.readouterr().out
    sid = ds.split_ids("test")[0]
    assert f"{sid}: Rack has " in printed and "m³ of free space available" in printed
    d = json.loads((out / f"{sid}.json").read_text())
    assert {"n_shelves", "n_box_stacks", "free_m3", "free_fraction", "shelves"} <= set(d)
    read_glb((out / f"{sid}.glb").read_bytes())
    assert (out / f"{sid}.ply").read_text().startswith("ply\n")
    assert (out / f"{sid}.png").stat().st_size > 1000

    # a corrupt layout file: one line naming it, the others still analysed, exit 1
    bad = ds.layout_path("front", ids[0])
    bad.write_bytes(b"not a numpy file")
    out2 = tmp_path / "out2"
    rc = main(["analyze", "--layouts", str(ds.root), "--out", str(out2), "--no-render"])
    cap = capsys.readouterr()
    assert rc == 1
    errors = [line for line in cap.err.splitlines() if "error" in line]
    assert len(errors) == 1 and str(bad) in errors[0]
    assert cap.out.count("Rack has") == len(ds.ids()) - 1
    summary = json.loads((out2 / "summary.json").read_text())
    assert summary["failed"] == 1 and summary["analysed"] == len(ds.ids()) - 1
    assert not (out2 / f"{ids[0]}.json").exists()

    # bad values in a layout: the same, naming the file and the value
    arr = np.load(ds.layout_path("top", ids[1]))
    arr[0, 0, 0] = 7
    np.save(ds.layout_path("top", ids[1]), arr)
    rc = main(["analyze", "--layouts", str(ds.root), "--out", str(out2), "--no-render", "--format", "none"])
    err = capsys.readouterr().err
    assert rc == 1 and "stray value(s) [7]" in err and str(ds.layout_path("top", ids[1])) in err

    # layouts whose photo is missing are still analysed (the photo only decorates the render)
    lone = ds.split_ids("train")[0]
    ds.image_path(lone).unlink()
    out3 = tmp_path / "out3"
    main(["analyze", "--layouts", str(ds.root), "--out", str(out3), "--no-render", "--format", "none"])
    assert f"{lone}: Rack has " in capsys.readouterr().out
    assert (out3 / f"{lone}.json").exists()


def analyze_counts(tmp_path, capsys, boxes, flag_sets) -> list[int]:
    """`racklay analyze --layouts` on one shelf holding `boxes`, once per list of extra flags: the
    box stacks it counts each time."""
    from racklay.cli import main

    top, front = L.stack_shelves([L.rasterize_shelf(SHELF, boxes, G)], 4, G)
    root = RackLayRoot(tmp_path / "one")
    root.write_sample("000000", image=np.zeros((64, 96, 3), np.uint8), top=top, front=front, meta={})
    counts = []
    for k, extra in enumerate(flag_sets):
        assert main(["analyze", "--layouts", str(root.root), "--out", str(tmp_path / f"o{k}"),
                     "--no-render", "--format", "none", *extra]) == 0
        counts.append(json.loads((tmp_path / f"o{k}" / "000000.json").read_text())["n_box_stacks"])
        capsys.readouterr()
    return counts


def test_cli_analyze_split_step_flag(tmp_path, capsys):
    """`--split-step` reaches the analysis: a wall of two touching stacks of different heights is
    two stacks by default and one with the cut off."""
    wall = [L.Box(-0.3, 0.0, 0.6, 0.5, 0.25), L.Box(0.3, 0.0, 0.6, 0.5, 0.5)]
    assert analyze_counts(tmp_path, capsys, wall, [[], ["--split-step", "0"]]) == [2, 1]


def test_cli_usage_errors(tmp_path, capsys):
    from racklay.cli import main

    assert main(["analyze", "--out", str(tmp_path)]) == 2
    assert "nothing to analyse" in capsys.readouterr().err
    # without --weights the shipped model runs; a photo that is not there is that photo's error
    assert main(["analyze", "x.png", "--out", str(tmp_path / "a")]) == 1
    err = capsys.readouterr().err
    assert "shipped model" in err and "x.png" in err
    assert main(["analyze", "--layouts", str(tmp_path / "nope"), "--out", str(tmp_path)]) == 2
    assert "nope" in capsys.readouterr().err


def test_cli_analyze_photos_with_a_checkpoint(tmp_path, capsys):
    torch = pytest.importorskip("torch")
    from racklay.checkpoint import save_checkpoint
    from racklay.cli import main
    from racklay.model import ModelConfig, build_model
    from racklay.toy import build_toy_dataset

    torch.manual_seed(0)
    cfg = ModelConfig(image_size=64, layout_size=64)
    w = tmp_path / "m.safetensors"
    save_checkpoint(w, build_model(cfg), cfg)
    ds = build_toy_dataset(tmp_path / "toy", n=2, seed=0, D=64)
    out = tmp_path / "out"
    rc = main(["analyze", str(ds.root / "Images"), "--weights", str(w), "--out", str(out), "--no-render"])
    printed = capsys.readouterr().out
    assert rc == 0, printed
    # a dataset folder: its Images/ of the split
    rc = main(["analyze", str(ds.root), "--split", "train", "--weights", str(w), "--out", str(tmp_path / "o2"),
               "--no-render", "--format", "none"])
    assert rc == 0 and capsys.readouterr().out.count("Rack has") == len(ds.split_ids("train"))
    for sid in ds.ids():
        d = json.loads((out / f"{sid}.json").read_text())
        assert d["grid"]["D"] == 64 and d["report"].startswith("Rack has ")
        assert f"{sid}: Rack has " in printed


def test_cli_analyze_stops_at_an_output_it_cannot_write_and_leaves_no_half_rack(tmp_path, capsys):
    """A rack's outputs are written whole or not at all, and an output that cannot be written
    stops the command with one line naming it (as predict does): the next racks would fail alike."""
    from racklay.cli import main
    from racklay.toy import build_toy_dataset

    ds = build_toy_dataset(tmp_path / "toy", n=5, seed=1, D=64)
    sid = ds.split_ids("test")[0]
    out = tmp_path / "out"
    (out / f"{sid}.glb").mkdir(parents=True)        # a folder where the GLB goes
    rc = main(["analyze", "--layouts", str(ds.root), "--split", "test", "--out", str(out), "--no-render"])
    cap = capsys.readouterr()
    assert rc == 2
    err = [line for line in cap.err.splitlines() if "error" in line]
    assert len(err) == 1 and f"{sid}.glb" in err[0], cap.err
    assert not (out / f"{sid}.json").exists() and "Rack has" not in cap.out
    afile = tmp_path / "afile"
    afile.write_text("")
    assert main(["analyze", "--layouts", str(ds.root), "--out", str(afile)]) == 2
    assert capsys.readouterr().err.strip() == f"racklay: error: {afile}: is a file, expected a folder (output folder)"
    assert main(["analyze", "--layouts", str(ds.root), "--weights", "w.safetensors", "--out", str(out)]) == 2
    assert "--layouts ROOT analyses ground-truth layouts (no model)" in capsys.readouterr().err


def test_step_segments_cuts_a_slope_once_not_into_a_staircase():
    # what a prediction's top edge looks like: two levels joined by a blurred step (a 0.6 m rise
    # over 20 columns), then a valley; the fit alone cuts each slope into narrow pieces
    from racklay.reasoning import step_segments

    up = np.linspace(0.4, 1.0, 22)[1:-1]
    h = np.r_[np.full(30, 0.4), up, np.full(30, 1.0)]
    staircase = step_segments(h, 0.08, 3)
    assert len(staircase) >= 5
    spans = step_segments(h, 0.08, 3, slope_fraction=1.0)
    assert len(spans) == 2 and spans[0] == (0, spans[1][0]) and spans[1][1] == len(h)
    assert abs(spans[1][0] - 40) <= 1                         # cut where the slope is half way up
    # a valley between two levels is three stacks; the short foot of a slope at an end belongs to
    # its level, a lower stack at an end stays a stack
    valley = np.r_[np.full(30, 1.0), up[::-1], np.full(15, 0.4), up, np.full(30, 1.0)]
    assert len(step_segments(valley, 0.08, 3, slope_fraction=1.0)) == 3
    foot = np.r_[0.85, 0.9, 0.95, np.full(30, 1.0)]
    assert len(step_segments(foot, 0.08, 3)) == 2
    assert step_segments(foot, 0.08, 3, slope_fraction=1.0) == step_segments(foot[::-1], 0.08, 3, slope_fraction=1.0) \
        == [(0, 33)]
    lower = np.r_[np.full(10, 0.5), np.full(30, 1.0)]
    assert step_segments(lower, 0.08, 3, slope_fraction=1.0) == [(0, 10), (10, 40)]
    # sharp steps between flat levels are cut as before: a staircase of flat cartons keeps its four stacks
    stairs = np.repeat([0.3, 0.5, 0.7, 0.9], 12)
    assert step_segments(stairs, 0.08, 3, slope_fraction=1.0) == step_segments(stairs, 0.08, 3) \
        == [(0, 12), (12, 24), (24, 36), (36, 48)]


def test_slope_rule_reads_a_stack_of_shrinking_items_as_one():
    # items stacked narrower upward (a wedding cake): the front view's top edge climbs in steps
    # narrower than min_stack_m (5 cm a side: 1.6 px), which the fit alone reads as extra stacks
    shelf = L.Shelf(2.0, 0.8, 1.2)
    boxes = [L.Box(0.0, 0.0, 0.7 - 0.1 * k, 0.5, 0.2, z0=0.2 * k) for k in range(4)]
    on, _ = one_shelf(boxes, shelf=shelf)
    assert len(on.boxes) == 1
    off, _ = one_shelf(boxes, shelf=shelf, cfg=ReasoningConfig(slope_fraction=0))
    assert len(off.boxes) > 1


def test_known_load_width_cuts_a_run_of_touching_loads_into_equal_stacks():
    # what v11 draws over a row of pallets on the test site: one box run with a smooth top (here
    # three touching loads of one height, which no step tells apart); told the loads' width, the
    # reading cuts the run into round(length / width) equal stacks
    from racklay.reasoning import load_cuts

    boxes = [L.Box(x, 0.0, 0.6, 0.5, 0.4) for x in (-0.6, 0.0, 0.6)]
    plain, _ = one_shelf(boxes)
    assert len(plain.boxes) == 1
    loads, _ = one_shelf(boxes, cfg=ReasoningConfig(load_width_m=0.6))
    got = sorted(loads.boxes, key=lambda q: q.x[0])
    assert len(got) == 3
    for q, b in zip(got, boxes):
        assert q.x == pytest.approx(b.x_range(), abs=RES) and q.z[1] == pytest.approx(b.sz, abs=RES)
    # a width a sixth off still reads three (1.8 m / 0.7 m rounds to 3), a run shorter than half a
    # load stays one
    assert len(one_shelf(boxes, cfg=ReasoningConfig(load_width_m=0.7))[0].boxes) == 3
    assert load_cuts(10, 0.03125, 0.8) == [] and load_cuts(100, 0.03125, 0.8) == [25, 50, 75]


def test_cli_analyze_load_width_flag(tmp_path, capsys):
    from racklay.cli import main

    row = [L.Box(x, 0.0, 0.6, 0.5, 0.4) for x in (-0.6, 0.0, 0.6)]
    assert analyze_counts(tmp_path, capsys, row, [[], ["--load-width", "0.6"]]) == [1, 3]
    with pytest.raises(SystemExit):
        main(["analyze", "--layouts", str(tmp_path / "one"), "--out", str(tmp_path / "o"), "--load-width", "-1"])
    assert "argument --load-width: must be >= 0, got -1" in capsys.readouterr().err


def test_layout_figure_reads_the_stacks_with_a_known_load_width(tmp_path):
    # `racklay predict --load-width`: the figure outlines a row of touching loads as loads
    from matplotlib.patches import Rectangle

    from racklay.viz import layout_figure

    lay = L.rasterize_shelf(SHELF, [L.Box(x, 0.0, 0.6, 0.5, 0.4) for x in (-0.6, 0.0, 0.6)], G)
    top, front = L.stack_shelves([lay], 4, G)
    counts = []
    for w in (None, 0.6):
        fig = layout_figure(None, top, front, grid=G, outline_stacks=True, load_width=w)
        counts.append([len([p for p in ax.patches if isinstance(p, Rectangle)]) for ax in fig.axes][4])
        labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert counts == [1, 3]
    assert labels[-1] == "box stack read (racklay analyze, loads 0.6 m wide)"
