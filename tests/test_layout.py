import numpy as np
import pytest

from racklay import layout as L


def test_grid_defaults_and_resolution():
    g = L.Grid()
    assert g.size == 512 and g.extent == 8.0
    assert g.res == pytest.approx(0.015625)  # 1.5625 cm / pixel


@pytest.mark.parametrize("size,extent", [(512, 8.0), (256, 8.0), (128, 4.0)])
def test_metres_pixel_round_trip(size, extent):
    g = L.Grid(size, extent)
    xs = np.linspace(-extent / 2, extent / 2, 37)
    np.testing.assert_allclose(g.col_to_x(g.x_to_col(xs)), xs, atol=1e-12)
    np.testing.assert_allclose(g.row_to_y(g.y_to_row(xs)), xs, atol=1e-12)
    np.testing.assert_allclose(g.row_to_z(g.z_to_row(xs)), xs, atol=1e-12)
    # column centres are symmetric about x = 0; rows go from far (+y) at the top to near
    c = g.centers()
    np.testing.assert_allclose(c, -c[::-1])
    assert g.row_centers()[0] > 0 > g.row_centers()[-1]
    assert g.x_to_col(0.0) == size / 2 and g.y_to_row(0.0) == size / 2


def test_rack_plane_shelf_frame_shift():
    """u from the rack's left edge <-> x from the shelf's centre line: the left edge is x = -W/2,
    the middle x = 0, the right edge x = +W/2; arrays work and the two are inverses."""
    W = 2.7
    assert L.u_to_x(0.0, W) == -1.35 and L.u_to_x(1.35, W) == 0.0 and L.u_to_x(W, W) == 1.35
    u = np.array([0.0, 0.4, 2.7])
    np.testing.assert_allclose(L.u_to_x(u, W), [-1.35, -0.95, 1.35])
    np.testing.assert_allclose(L.x_to_u(L.u_to_x(u, W), W), u, atol=1e-15)
    assert L.x_to_u(-1.35, W) == 0.0


def test_front_offset_shelf_frame_shift():
    """A box's distance behind the board's front edge <-> shelf-frame y: the front edge is
    y = -depth/2 (the camera's side), the back edge +depth/2, and the two are inverses."""
    d = 0.9
    assert L.offset_to_y(0.0, d) == -0.45 and L.offset_to_y(0.9, d) == 0.45
    off = np.array([0.0, 0.2, 0.9])
    np.testing.assert_allclose(L.y_to_offset(L.offset_to_y(off, d), d), off, atol=1e-15)


def test_bad_grid_rejected():
    with pytest.raises(ValueError):
        L.Grid(511)
    with pytest.raises(ValueError):
        L.Grid(512, 0)


def test_axis_rect_exact_pixel_count():
    g = L.Grid(512, 8.0)  # 1.5625 cm pixels
    canvas = np.zeros((512, 512), np.uint8)
    # 1.0 m x 0.5 m = 64 x 32 pixels exactly, centred
    L.fill_axis_rect(canvas, g, -0.5, 0.5, -0.25, 0.25, 1)
    assert np.count_nonzero(canvas) == 64 * 32
    rows, cols = np.nonzero(canvas)
    assert cols.min() == 256 - 32 and cols.max() == 256 + 31
    assert rows.min() == 256 - 16 and rows.max() == 256 + 15


def test_adjacent_rects_tile_without_gap_or_overlap():
    g = L.Grid(128, 8.0)
    a = L.fill_axis_rect(np.zeros((128, 128), np.uint8), g, -1.0, 0.13, 0, 1, 1)
    b = L.fill_axis_rect(np.zeros((128, 128), np.uint8), g, 0.13, 1.0, 0, 1, 1)
    both = L.fill_axis_rect(np.zeros((128, 128), np.uint8), g, -1.0, 1.0, 0, 1, 1)
    assert not np.any(a & b)
    np.testing.assert_array_equal(a | b, both)


def test_top_view_far_side_on_top_and_x_to_the_right():
    g = L.Grid(64, 8.0)  # 12.5 cm pixels
    shelf = L.Shelf(length=4.0, depth=2.0, clear_height=1.0)
    # a box in the far-right quadrant of the shelf
    box = L.Box(cx=1.0, cy=0.5, sx=0.5, sy=0.5, sz=0.5)
    lay = L.rasterize_shelf(shelf, [box], g)
    rows, cols = np.nonzero(lay.top == L.BOX)
    assert cols.min() >= 32 and rows.max() < 32  # right half, top half (far)
    assert len(rows) == 16  # 0.5 m / 0.125 m = 4 px a side
    assert np.count_nonzero(lay.top == L.SHELF) == 32 * 16 - 16
    # front view: same columns, box from the board (centre row) upward
    frows, fcols = np.nonzero(lay.front == L.BOX)
    assert set(fcols) == set(cols)
    assert frows.max() == 31 and frows.min() == 28
    # free space: length x (clear height + 5 cm pad) upward from the centre row
    free = (lay.front > 0)
    assert free[:32].any() and not free[32:].any()
    # row centres at 0.0625, 0.1875, ..., 0.9375 m lie below 1.05 m; 1.0625 m does not
    assert np.count_nonzero(free.any(axis=1)) == 8


def test_oriented_box_area_and_symmetry():
    g = L.Grid(512, 8.0)
    m0 = L.oriented_rect_mask(g, 0.0, 0.0, 1.0, 0.5, 0.0)
    assert m0.sum() == 64 * 32
    m45 = L.oriented_rect_mask(g, 0.0, 0.0, 1.0, 0.5, np.pi / 4)
    assert abs(int(m45.sum()) - 64 * 32) < 0.03 * 64 * 32  # area preserved up to the pixel boundary
    m90 = L.oriented_rect_mask(g, 0.0, 0.0, 1.0, 0.5, np.pi / 2)
    np.testing.assert_array_equal(m90, L.oriented_rect_mask(g, 0.0, 0.0, 0.5, 1.0, 0.0))
    # rotated box's front-view x-range matches its footprint's column span
    b = L.Box(cx=0.3, cy=0.1, sx=1.0, sy=0.5, sz=0.4, yaw=0.4)
    lay = L.rasterize_shelf(L.Shelf(3, 2, 1), [b], g)
    tc = np.nonzero((lay.top == L.BOX).any(axis=0))[0]
    fc = np.nonzero((lay.front == L.BOX).any(axis=0))[0]
    assert abs(tc.min() - fc.min()) <= 1 and abs(tc.max() - fc.max()) <= 1


def test_a_window_draws_the_part_of_the_shelf_a_photo_shows_recentred():
    """window=(x0, x1): the shelf as far as the frame shows it (the labelling guide's rule), a
    shelf x1 - x0 long, centred, whose boxes the window's ends cut; the whole shelf's window is
    the shelf itself."""
    g = L.Grid(64, 8.0)  # 12.5 cm pixels
    shelf = L.Shelf(length=4.0, depth=1.0, clear_height=1.0)
    boxes = [L.Box(cx=-1.5, cy=0.0, sx=0.5, sy=0.5, sz=0.5),        # cut off
             L.Box(cx=0.0, cy=0.0, sx=1.0, sy=0.5, sz=0.75),        # cut by the window's left end
             L.Box(cx=1.25, cy=0.0, sx=0.5, sy=0.5, sz=0.5, yaw=0.3)]
    whole = L.rasterize_shelf(shelf, boxes, g)
    same = L.rasterize_shelf(shelf, boxes, g, window=(-3.0, 3.0))
    np.testing.assert_array_equal(same.top, whole.top)
    np.testing.assert_array_equal(same.front, whole.front)

    part = L.rasterize_shelf(shelf, boxes, g, window=(0.25, 2.0))     # 1.75 m, centre x = 1.125
    assert L.shelf_lengths(part.front[None], g)[0] == pytest.approx(1.75, abs=g.res)
    cols = np.nonzero((part.front > 0).any(axis=0))[0]
    assert (cols.min(), cols.max()) == (25, 38)                       # -0.875 .. 0.875 m, centred
    # every kept column is the whole shelf's column 1.125 m (9 pixels) to the right
    np.testing.assert_array_equal(part.front[:, 25:39], whole.front[:, 34:48])
    np.testing.assert_array_equal(part.top[:, 25:39], whole.top[:, 34:48])
    assert not part.top[:, :25].any() and not part.top[:, 39:].any()
    with pytest.raises(ValueError, match="does not overlap"):
        L.rasterize_shelf(shelf, boxes, g, window=(2.5, 3.0))


def test_box_outside_grid_is_clipped_not_an_error():
    g = L.Grid(64, 8.0)
    m = L.oriented_rect_mask(g, 10.0, 0.0, 1.0, 1.0, 0.3)
    assert not m.any()


def test_stack_missing_shelves_are_background():
    g = L.Grid(32, 8.0)
    one = L.rasterize_shelf(L.Shelf(2, 1, 0.5), [], g)
    top, front = L.stack_shelves([one, one], R=4, grid=g)
    assert top.shape == (4, 32, 32)
    assert top[:2].any() and not top[2:].any() and not front[2:].any()
    assert L.visible_shelf_count(top) == 2
    with pytest.raises(L.LayoutError):
        L.stack_shelves([one] * 5, R=4, grid=g)


def test_encode_decode_round_trip_and_strictness():
    ids = np.array([[0, 1], [2, 1]], np.uint8)
    vals = L.encode(ids)
    np.testing.assert_array_equal(vals, [[0, 115], [255, 115]])
    np.testing.assert_array_equal(L.decode(vals), ids)
    with pytest.raises(L.LayoutError, match="114"):
        L.decode(np.array([0, 114, 255], np.uint8), "x.npy")
    with pytest.raises(L.LayoutError):
        L.encode(np.array([3]))
    with pytest.raises(L.LayoutError, match=r"\[3\]"):
        L.encode(np.array([[0, 3]], np.uint8))
    stack = np.random.default_rng(0).integers(0, 3, (4, 16, 16), dtype=np.uint8)
    for arr in (stack, stack.astype(np.int64), stack[:, ::2, ::-1]):   # any dtype, any strides
        out = L.encode(arr)
        assert out.dtype == np.uint8 and np.array_equal(out, L.FILE_VALUES[arr.astype(np.intp)])
    with pytest.raises(L.LayoutError, match="dtype"):
        L.check_stack(np.zeros((4, 8, 8), np.float32))
    with pytest.raises(L.LayoutError, match="shape"):
        L.check_stack(np.zeros((8, 8), np.uint8))


def test_hflip_matches_mirrored_scene():
    g = L.Grid(128, 8.0)
    shelf = L.Shelf(2.0, 1.0, 0.6)
    b = L.Box(cx=0.55, cy=0.2, sx=0.4, sy=0.3, sz=0.3, yaw=0.3)
    mirrored = L.Box(cx=-0.55, cy=0.2, sx=0.4, sy=0.3, sz=0.3, yaw=-0.3)
    lay = L.rasterize_shelf(shelf, [b], g)
    mir = L.rasterize_shelf(shelf, [mirrored], g)
    flipped = L.hflip_layouts(np.stack([lay.top, lay.front]))
    # a mirrored scene equals the flipped layout up to pixels whose centre lies exactly on an edge
    assert np.mean(flipped[0] != mir.top) < 0.002
    np.testing.assert_array_equal(flipped[1], mir.front)
    np.testing.assert_array_equal(L.hflip_layouts(flipped), np.stack([lay.top, lay.front]))


def test_resize_layouts_nearest_keeps_metric_convention():
    g512, g128 = L.Grid(512), L.Grid(128)
    shelf, boxes = L.Shelf(2.0, 1.0, 0.5), [L.Box(0.5, 0.0, 0.5, 0.5, 0.25)]
    big = L.rasterize_shelf(shelf, boxes, g512).top
    small = L.rasterize_shelf(shelf, boxes, g128).top
    down = L.resize_layouts(big[None], 128)[0]
    assert set(np.unique(down)) <= {0, 1, 2}
    assert np.mean(down != small) < 0.01
