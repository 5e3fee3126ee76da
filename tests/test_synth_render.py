"""WareSynth rendering options: MSAA, the user's texture folder, the proxy-real camera effects
(distortion keeps the per-pixel maps aligned with the image), deterministic renders."""
from __future__ import annotations

import numpy as np
import pytest

from racklay.synth.generate import Generator, render_padding
from racklay.synth.recipe import RecipeError, load_recipe
from racklay.synth.scene import sample_scene

SMALL = ["image_width=200", "image_height=120", "focal_px=[140,220]", "layout_size=64"]


def test_msaa_changes_only_the_rgb(tmp_path):
    base = Generator(load_recipe("complex", SMALL + ["antialias=0"]), 0, tmp_path / "a")
    msaa = Generator(load_recipe("complex", SMALL + ["antialias=4"]), 0, tmp_path / "b")
    try:
        s0, rgb0, maps0, *_ = base.make(1)
        s1, rgb1, maps1, *_ = msaa.make(1)
    finally:
        base.close()
        msaa.close()
    assert np.array_equal(maps0["instance"], maps1["instance"])
    assert np.array_equal(maps0["depth"], maps1["depth"])
    assert np.array_equal(maps0["normals"], maps1["normals"])   # the G-buffer pass = the colour pass's G-buffer
    diff = np.any(rgb0 != rgb1, axis=-1)
    edges = np.zeros_like(diff)
    inst = maps0["instance"]
    edges[:, 1:] |= inst[:, 1:] != inst[:, :-1]
    edges[1:, :] |= inst[1:, :] != inst[:-1, :]
    assert diff.any() and diff[edges].mean() > diff[~edges].mean()  # MSAA works on edges


def test_same_scene_renders_identically(tmp_path):
    g = Generator(load_recipe("complex", SMALL), 0, tmp_path / "a")
    try:
        a = g.make(2)[1]
        g.make(3)
        b = g.make(2)[1]
    finally:
        g.close()
    assert np.array_equal(a, b)


def test_user_texture_folder(tmp_path):
    from racklay.atomic import atomic_save_png
    from racklay.synth.textures import build_bank

    folder = tmp_path / "tex"
    atomic_save_png(folder / "a.png", np.full((40, 60, 3), (250, 0, 250), np.uint8))
    bank = build_bank("warehouse", 0, str(folder))
    magenta = [i for i, l in enumerate(bank.layers) if (l == (250, 0, 250)).all()]
    assert magenta and all(magenta[0] in bank.materials[f"carton_{k}"].side for k in
                           ("small", "medium", "long", "flat", "tall", "large"))
    r = load_recipe("complex", SMALL + [f"texture_dir={folder}"])
    g = Generator(r, 0, tmp_path / "out")
    try:
        rgb = g.make(0)[1]
    finally:
        g.close()
    c = rgb.astype(int)
    assert ((c[..., 0] - c[..., 1] > 40) & (c[..., 2] - c[..., 1] > 40)).sum() > 20  # magenta carton sides
    with pytest.raises(RecipeError, match="not found"):
        load_recipe("complex", ["texture_dir=/no/such/folder"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="holds no images"):
        build_bank("warehouse", 0, str(tmp_path / "empty"))
    # an empty texture folder is refused with the recipe, before `racklay synth` makes its output
    # folder (a skeleton left behind used to make the corrected re-run refuse it)
    from racklay.cli import main as racklay_main

    out = tmp_path / "synth"
    assert racklay_main(["synth", "--recipe", "complex", "--n", "1", "--out", str(out),
                         "--set", f"texture_dir={tmp_path / 'empty'}", "--no-progress"]) == 2
    assert not out.exists()


def test_proxy_real_distortion_keeps_maps_aligned(tmp_path):
    r = load_recipe("proxy_real", SMALL + ["distortion_k1=[-0.15,-0.15]", "noise_std=[0,0]", "blur_sigma=[0,0]",
                                           "jpeg_quality=[0,0]", "vignetting=[0,0]", "exposure=[1,1]",
                                           "white_balance=0"])
    assert render_padding(r)[0] > 0
    undist = load_recipe("proxy_real", SMALL + ["distortion_k1=[0,0]"])
    g = Generator(r, 0, tmp_path / "a")
    try:
        scene, rgb, maps, top, front, meta, *_ = g.make(0)
    finally:
        g.close()
    inst = maps["instance"]
    assert meta["camera"]["distortion_k1"] == -0.15 and inst.shape == rgb.shape[:2]
    assert inst.all(), "barrel distortion must not sample outside the (padded) render"
    # the image edges follow the instance boundaries: colour jumps sit on id changes
    jump = np.abs(np.diff(rgb.astype(int), axis=1)).sum(-1) > 60
    idchange = inst[:, 1:] != inst[:, :-1]
    near = idchange.copy()
    near[:, 1:] |= idchange[:, :-1]
    near[:, :-1] |= idchange[:, 1:]
    assert jump.sum() > 50 and (jump & near).sum() / jump.sum() > 0.6
    # layouts do not depend on the distortion
    s2 = sample_scene(undist, 0, 0)
    assert [o.layout_box for o in scene.objects if o.shelf >= 0] == [o.layout_box for o in s2.objects if o.shelf >= 0]
    # visible 2D boxes lie inside the (distorted) amodal boxes
    for o in meta["objects"]:
        if o["bbox_visible"] and o["bbox_amodal"] and o["truncation"] == 0:
            x0, y0, x1, y1 = o["bbox_visible"]
            a0, b0, a1, b1 = o["bbox_amodal"]
            assert x0 >= a0 - 1.5 and y0 >= b0 - 1.5 and x1 <= a1 + 1.5 and y1 <= b1 + 1.5, o["id"]


def test_wide_lens_distortion_is_bounded_and_inverted_exactly():
    """A wide lens (focal 0.4 x the image width) with strong barrel k1: sample_scene bounds k1 so
    the farthest corner's pinhole radius is stretched at most MAX_CORNER_STRETCH times (before: the
    model folded, the corners were garbage and the padded render was 6x the image); the maps'
    source of every output pixel lies inside the padded render and distorts back onto that pixel."""
    from racklay.synth.effects import MAX_CORNER_STRETCH, distort_points, distortion_maps, k1_limit

    r = load_recipe("proxy_real", ["image_width=200", "image_height=120", "focal_px=[80,80]",
                                   "distortion_k1=[-0.3,-0.3]", "layout_size=64"])
    px, py = render_padding(r)
    assert px <= 0.25 * 100 + 2 and py <= 0.25 * 60 + 2       # at most the bounded stretch of a half-image
    cam = sample_scene(r, 0, 0).camera
    assert cam.k1 == pytest.approx(k1_limit(cam.K, 200, 120)) and cam.k1 > -0.3
    mx, my = distortion_maps(cam.K, cam.k1, 200, 120, offset=(px, py))
    assert mx.min() >= -0.5 and mx.max() <= 200 + 2 * px - 0.5 and my.min() >= -0.5 and my.max() <= 120 + 2 * py - 0.5
    # corner: undistorted source -> distorted again = the output pixel's centre
    src = np.array([[mx[0, 0] + 0.5 - px, my[0, 0] + 0.5 - py], [mx[-1, -1] + 0.5 - px, my[-1, -1] + 0.5 - py]])
    np.testing.assert_allclose(distort_points(cam.K, cam.k1, src), [[0.5, 0.5], [199.5, 119.5]], atol=1e-3)
    K = cam.K
    stretch = np.hypot(*(src[0] - K[:2, 2])) / np.hypot(0.5 - K[0, 2], 0.5 - K[1, 2])
    assert stretch <= MAX_CORNER_STRETCH + 1e-6
    # a milder k1 the lens can take is left as drawn
    mild = load_recipe("proxy_real", ["image_width=200", "image_height=120", "focal_px=[80,80]",
                                      "distortion_k1=[-0.02,-0.02]", "layout_size=64"])
    assert sample_scene(mild, 0, 0).camera.k1 == -0.02


def _depth_and_normals(z: np.ndarray) -> np.ndarray:
    """Camera-frame normals (uint8, as the G-buffer stores them) of fronto-parallel surfaces."""
    n = np.zeros(z.shape + (3,), np.uint8)
    n[..., :2], n[..., 2] = 128, 0       # (0, 0, -1): facing the camera
    n[z == 0] = 0
    return n


def test_ambient_occlusion_darkens_recesses_not_open_faces():
    """A wall 3 m away, two loads 1.2 m in front of it with a 12 cm slot between them: the wall
    seen through the slot is occluded, open wall far from the loads and the loads' own faces are
    not (no self-occlusion of a plane), and nothing is drawn where the image shows nothing."""
    from racklay.synth.render import ambient_occlusion, occlude

    H, W, f = 120, 200, 150.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    z = np.full((H, W), 3.0, np.float32)
    slot = int(round(0.12 * f / 1.8))                           # 12 cm at 1.8 m in pixels
    z[20:100, 40:100 - slot // 2] = 1.8
    z[20:100, 100 + slot // 2:160] = 1.8
    z[:, 195:] = 0                                               # nothing there
    ao = ambient_occlusion(z, _depth_and_normals(z), K)
    assert ao.shape == (H, W) and ao.dtype == np.float32 and 0 <= ao.min() and ao.max() <= 1
    in_slot = ao[40:80, 99:101].mean()
    open_wall, load_face = ao[40:80, 5:15].mean(), ao[40:80, 60:70].mean()
    assert open_wall > 0.95 and load_face > 0.95
    assert in_slot < open_wall - 0.3
    assert np.all(ao[:, 196:] == 1)
    rgb = np.full((H, W, 3), 200, np.uint8)
    assert np.array_equal(occlude(rgb, ao, 0.0), rgb)
    dark = occlude(rgb, ao, 2.0)
    assert dark[60, 100, 0] < occlude(rgb, ao, 1.0)[60, 100, 0] < 200 and dark[60, 10, 0] >= 190


def test_ambient_occlusion_changes_only_the_rgb_and_is_off_by_default(tmp_path):
    """The recipe key darkens the image and nothing else (maps, layouts and meta geometry equal);
    drawn last, it leaves every other draw of the scene as it was; the meta records it."""
    off = Generator(load_recipe("pallet", SMALL), 0, tmp_path / "a")
    on = Generator(load_recipe("pallet", SMALL + ["ambient_occlusion=[2,2]"]), 0, tmp_path / "b")
    try:
        s0, rgb0, maps0, top0, front0, meta0, *_ = off.make(1)
        s1, rgb1, maps1, top1, front1, meta1, *_ = on.make(1)
    finally:
        off.close()
        on.close()
    assert s0.occlusion == 0 and s1.occlusion == 2.0 and meta1["ambient_occlusion"] == 2.0
    for key in maps0:
        assert np.array_equal(maps0[key], maps1[key])
    assert np.array_equal(top0, top1) and np.array_equal(front0, front1)
    assert s0.camera.K.tolist() == s1.camera.K.tolist() and len(s0.objects) == len(s1.objects)
    ratio = (rgb1.astype(float).sum(-1) + 1) / (rgb0.astype(float).sum(-1) + 1)
    assert np.median(ratio) < 1 and np.mean(ratio < 0.5) > 0.01      # darker, recesses much darker


def test_only_the_part_the_lens_reads_is_drawn_and_the_sample_is_the_same(tmp_path, monkeypatch):
    """The generator draws only the part of the padded render that the lens distortion reads
    (or the unpadded image without distortion): every file of a sample must be what drawing
    the whole padded frame gives, bit for bit."""
    from racklay.synth import generate

    r = load_recipe("pallet", SMALL + ["focal_px=[90,220]", "distortion_k1=[-0.12,0.05]"])
    assert min(render_padding(r)) > 0
    parts = Generator(r, 0, tmp_path / "a")
    try:
        got = [parts.make(i) for i in range(4)]
        drawn = []
        monkeypatch.setattr(generate, "source_region", lambda maps, size: (0, 0, *size))   # the whole frame
        monkeypatch.setattr(parts.renderer, "render", _recording(parts.renderer.render, drawn))
        whole = [parts.make(i) for i in range(4)]
    finally:
        parts.close()
    assert all(region == (0, 0, parts.renderer.W, parts.renderer.H) for region in drawn)
    for a, b in zip(got, whole):
        assert np.array_equal(a[1], b[1])                            # rgb
        for k in ("instance", "depth", "normals"):
            assert np.array_equal(a[2][k], b[2][k]), k
        assert a[5]["objects"] == b[5]["objects"]


def _recording(render, drawn):
    def rec(scene, camera=None, region=None):
        drawn.append(region)
        return render(scene, camera, region=region)
    return rec


def test_render_region_is_the_crop_of_the_whole_frame(tmp_path):
    g = Generator(load_recipe("complex", SMALL), 0, tmp_path / "a")
    try:
        scene = sample_scene(g.recipe, 0, 1)
        full = g.renderer.render(scene)
        part = g.renderer.render(scene, region=(30, 17, 151, 90))
        with pytest.raises(ValueError, match="not inside"):
            g.renderer.render(scene, region=(0, 0, 201, 120))
    finally:
        g.close()
    for k in ("rgb", "instance", "depth", "normals"):
        assert np.array_equal(getattr(part, k), getattr(full, k)[17:90, 30:151]), k


def test_distortion_maps_of_a_centred_camera_are_solved_per_pixel_exactly():
    """The maps of a centred principal point are solved on one quadrant and mirrored: the same
    bits as the fixed-point solve of every pixel (odd and even image sizes)."""
    from racklay.synth.effects import distortion_maps, undistort_normalised

    for W, H, k1 in ((200, 120, -0.1), (201, 121, 0.04), (470, 280, -0.03)):
        f = 0.6 * W
        K = np.array([[f, 0, W / 2], [0, 1.01 * f, H / 2], [0, 0, 1]])
        mx, my = distortion_maps(K, k1, W, H, offset=(7, 5))
        u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        xu, yu = undistort_normalised((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], k1)
        assert np.array_equal(mx, (xu * K[0, 0] + K[0, 2] + 7 - 0.5).astype(np.float32))
        assert np.array_equal(my, (yu * K[1, 1] + K[1, 2] + 5 - 0.5).astype(np.float32))


def test_edge_antialias_averages_exactly_the_pixels_next_to_an_id_change():
    from racklay.synth.effects import edge_antialias

    rng = np.random.default_rng(0)
    inst = np.zeros((40, 60), np.uint32)
    inst[10:25, 20:45] = 7
    inst[30:, :5] = 3
    rgb = rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
    out = edge_antialias(rgb, inst)
    pad = np.pad(rgb.astype(np.uint16), ((1, 1), (1, 1), (0, 0)), mode="reflect")   # cv2.blur's default border
    box = sum(pad[dy:dy + 40, dx:dx + 60] for dy in range(3) for dx in range(3))
    blur = ((box + 4) // 9).astype(np.uint16)
    # c: an id change to the left or above; a pixel is softened when it or its right, lower or
    # lower-right neighbour has one (the two pixels at every id change, and the corner between)
    c = np.zeros((41, 61), bool)
    c[:40, 1:60] |= inst[:, 1:] != inst[:, :-1]
    c[1:40, :60] |= inst[1:] != inst[:-1]
    edge = c[:40, :60] | c[:40, 1:] | c[1:, :60] | c[1:, 1:]
    want = np.where(edge[..., None], (rgb + blur) // 2, rgb)
    assert edge.sum() > 100 and np.abs(out.astype(int) - want.astype(int)).max() <= 1
    assert np.array_equal(out[~edge], rgb[~edge])


def test_two_renderers_in_one_process_each_draw_their_own_frame(tmp_path):
    """Each GL renderer makes its own context current to draw: a second one made in the same
    process (a notebook, a test, an A/B of two recipes) must not change what the first draws."""
    first = Generator(load_recipe("complex", SMALL), 0, tmp_path / "a")
    try:
        alone = first.make(1)[1]
        second = Generator(load_recipe("complex", SMALL + ["antialias=4"]), 0, tmp_path / "b")
        try:
            after = first.make(1)[1]
            other = second.make(1)[1]
            again = first.make(1)[1]
        finally:
            second.close()
    finally:
        first.close()
    assert np.array_equal(after, alone) and np.array_equal(again, alone)
    assert not np.array_equal(other, alone)


def test_sensor_noise_is_a_function_of_its_seed_with_the_asked_spread(monkeypatch):
    from racklay.synth import effects

    a, b = effects.gaussian_noise((120, 200, 3), 5), effects.gaussian_noise((120, 200, 3), 5)
    c = effects.gaussian_noise((120, 200, 3), 6)
    assert a.dtype == np.float32 and np.array_equal(a, b) and not np.array_equal(a, c)
    assert abs(float(a.std()) - 1) < 0.02 and abs(float(a.mean())) < 0.02
    a[0, 0, 0] = 1e6   # the caller's copy: the bank stays as it was
    assert np.array_equal(effects.gaussian_noise((120, 200, 3), 5), b)
    monkeypatch.setattr(effects, "NOISE_BANK_SIZE", 1000)
    effects._noise_bank.cache_clear()
    try:   # larger than the bank: drawn afresh, still by the seed
        big = effects.gaussian_noise((40, 40), 5)
        assert np.array_equal(big, effects.gaussian_noise((40, 40), 5)) and abs(float(big.std()) - 1) < 0.1
    finally:
        effects._noise_bank.cache_clear()
    img = np.full((60, 80, 3), 128, np.uint8)
    out = effects.photometric(img, {"noise_std": 6.0, "noise_seed": 1}).astype(np.float32) - 128
    assert 5.0 < float(out.std()) < 7.0
