"""annotate textures: the labelled boxes' faces, rectified and tiled, become WareSynth carton
textures; nothing half-written, the split respected, and the folder usable as texture_dir."""
import numpy as np
import pytest

from annotate.cli import main as annotate_main
from annotate.textures import TARGET_LUMA, TEXTURE_PX, export_textures
from racklay.atomic import encode_png
from racklay.data import read_image
from racklay.synth.recipe import texture_files
from test_annotate_export import make_project
from test_annotate_geometry import BOXES, Camera

#: tiles per photo of the test rack's six boxes at the default 0.45 m (widths 0.45, 0.6, 0.4,
#: 0.7, 0.7, 1.0 m: 1, 1, 1, 2, 2, 2 tiles; every height rounds to one)
TILES = 9


def test_textures_are_the_rectified_box_faces_tiled_and_levelled(tmp_path, capsys):
    proj = make_project(tmp_path, 2)
    (proj.root / "p0.png").write_bytes(encode_png(np.full((480, 640, 3), 60, np.uint8)))   # a dim photo
    # photo 1: dark left of the rack's x = 0.75 m, bright right of it: the border runs through the
    # middle of the left tile of box 5 (shelf 2, x 0.5-1.5 m: tiles 0.5-1.0 and 1.0-1.5 m)
    from annotate import geometry as G

    scene = G.build_scene(proj.read_annotation("p1.png"), proj.settings)
    border = int(round(scene.plane.to_image([[0.75, scene.boxes[5].v0]])[0, 0]))
    img = np.full((480, 640, 3), 40, np.uint8)
    img[:, border:] = 200
    (proj.root / "p1.png").write_bytes(encode_png(img))
    out = tmp_path / "tex"
    assert annotate_main(["textures", str(proj.root), "--out", str(out)]) == 0
    assert f"wrote {2 * TILES} texture(s) from 2 photo(s)" in capsys.readouterr().out
    files = texture_files(str(out))                  # what `racklay synth --set texture_dir=` reads
    assert len(files) == 2 * TILES
    for f in files:
        t = read_image(f)
        assert t.shape == (TEXTURE_PX, TEXTURE_PX, 3)
        assert abs(np.median(t.mean(2)) - TARGET_LUMA) < 3     # one brightness, whatever the photo's
    # rectified: the left tile of box 5 is dark in its left half and bright in its right half, the
    # border at its middle column; the right tile is one brightness
    left, right = (read_image(out / f"p1_b5_{k:02d}.jpg").mean(2) for k in (0, 1))
    col = left.mean(0)
    assert col[:120].max() < 0.5 * col[136:].min()
    assert np.ptp(right.mean(0)[8:-8]) < 10
    # a non-empty folder is refused, and nothing was written there
    assert annotate_main(["textures", str(proj.root), "--out", str(out)]) == 2
    assert "not a new or empty folder" in capsys.readouterr().err and len(texture_files(str(out))) == 2 * TILES


def test_textures_take_only_the_split_asked_and_leave_nothing_on_failure(tmp_path):
    proj = make_project(tmp_path, 3, ["done", "done", "in progress"])
    res = export_textures(proj, tmp_path / "train", split_of={"p0.png": "train", "p1.png": "test"}, split="train")
    assert res["photos"] == 1 and res["textures"] == TILES
    assert sorted({p.name.split("_")[0] for p in (tmp_path / "train").iterdir()}) == ["p0"]
    with pytest.raises(ValueError, match="needs --split-file"):
        export_textures(proj, tmp_path / "x", split="train")
    with pytest.raises(ValueError, match=r"no photo with status done, approved in split 'val' \(the split file names: train\)"):
        export_textures(proj, tmp_path / "x", split_of={"p0.png": "train"}, split="val")
    # a rack that cannot be rebuilt names its annotation file, and no folder is left behind
    ann = proj.read_annotation("p1.png")
    ann["rack"]["corners"] = [[10, 10], [20, 10], [30, 10], [40, 10]]      # all on one line
    proj.save(ann)
    with pytest.raises(ValueError, match=r"p1\.png\.json: cannot rebuild the rack"):
        export_textures(proj, tmp_path / "y")
    assert not (tmp_path / "y").exists() and not list(tmp_path.glob(".y.*"))


def test_a_box_the_frame_cuts_gives_the_tiles_of_its_visible_part():
    """Its appearance is still a texture (its size is not, which the coverage report minds)."""
    from annotate import geometry as G
    from annotate.textures import box_tiles, face_texture
    from test_annotate_geometry import SETTINGS, clicks

    ann = clicks(Camera([1.0, -3.2, 1.0], [1.0, 0, 1.0]))
    scene = G.build_scene(ann, SETTINGS)
    img = np.full((480, 640, 3), 90, np.uint8)
    b = scene.boxes[5]
    assert [len(box_tiles(x)) for x in scene.boxes] == [1, 1, 1, 2, 2, 2] and len(BOXES) == 6
    whole = [face_texture(img, scene.plane, r) for r in box_tiles(b)]
    assert all(t is not None for t in whole)
    assert not any(G.cut_by_frame(scene.plane, b, (640, 480)))
    # the same face seen in a photo cropped through the box: the tile outside the frame is left out
    u_mid = (b.u0 + b.u1) / 2
    x_mid = scene.plane.to_image([[u_mid, b.v0]])[0, 0]
    cropped = img[:, : int(x_mid) + 2]
    got = [face_texture(cropped, scene.plane, r) for r in box_tiles(b)]
    assert got[0] is not None and got[1] is None


def test_photos_sharing_a_stem_keep_both_their_textures_and_a_tile_of_millimetres_is_refused(tmp_path, capsys):
    """'a.jpg' and 'a.png' (a camera's JPEG beside its PNG export) wrote the same file names, the
    second photo's textures silently replacing the first's."""
    import cv2

    proj = make_project(tmp_path, 2, names=["a.png", "b.png"])
    ok, jpg = cv2.imencode(".jpg", np.full((480, 640, 3), 120, np.uint8))
    (proj.root / "a.jpg").write_bytes(jpg.tobytes())
    from test_annotate_geometry import clicks

    ann = clicks(Camera([1.0, -3.2, 1.0], [1.0, 0, 1.0]))
    ann.update(image="a.jpg", status="done")
    proj.save(ann)
    res = export_textures(proj, tmp_path / "tex")
    assert res["photos"] == 3 and res["textures"] == 3 * TILES
    assert len(texture_files(str(tmp_path / "tex"))) == 3 * TILES
    assert {p.name.rsplit("_b", 1)[0] for p in (tmp_path / "tex").iterdir()} == {"a_jpg", "a_png", "b"}
    rc = annotate_main(["textures", str(proj.root), "--out", str(tmp_path / "t2"), "--tile", "0.002"])
    err = capsys.readouterr().err
    assert rc == 2 and "--tile: 0.002 m is not a carton face's size" in err and not (tmp_path / "t2").exists()
