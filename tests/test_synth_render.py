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
