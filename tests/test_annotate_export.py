"""annotate export / import: a project exported is a clean RackLay dataset whose layouts are the
geometry's, and importing it back attaches the same layouts read-only."""
import json

import numpy as np
import pytest

from annotate.cli import main as annotate_main
from annotate.dataset import split_ids
from annotate.store import Project
from racklay import layout as L
from racklay.atomic import encode_png
from racklay.data import RackLayRoot, check_dataset
from test_annotate_geometry import Camera, clicks, iou, true_layouts


def make_project(tmp_path, n=5, statuses=None, names=None):
    root = tmp_path / "proj"
    root.mkdir()
    cam = Camera([1.0, -3.2, 1.0], [1.0, 0, 1.0])
    proj = Project(root)
    proj.save_settings(dict(proj.settings, D=256, extent=4.0))
    for k in range(n):
        name = names[k] if names else f"p{k}.png"
        (root / name).write_bytes(encode_png(np.full((480, 640, 3), 30 * k % 250, np.uint8)))
        ann = clicks(cam)
        ann["image"] = name
        ann["status"] = (statuses or ["done"] * n)[k]
        proj.save(ann)
    return proj


def test_export_check_data_clean(tmp_path, capsys):
    proj = make_project(tmp_path, 5, ["done", "approved", "in progress", "done", "needs review"])
    out = tmp_path / "ds"
    rc = annotate_main(["export", str(proj.root), "--out", str(out), "--split", "train=2,test=1", "--seed", "3"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "exported 3 image(s)" in printed
    assert "left out: 1 with status in progress; 1 with status needs review" in printed
    rep = check_dataset(out)
    assert rep.ok, rep.problems
    assert rep.samples == 3 and rep.splits == {"train": 2, "test": 1} and (rep.R, rep.D) == (4, 256)
    ds = RackLayRoot(out)
    ttop, tfront = true_layouts()
    for view, t in (("top", ttop), ("front", tfront)):
        got = ds.read_layouts(view, "000001")
        for i in range(3):
            assert iou(got[i] == L.BOX, t[i] == L.BOX) >= 0.9
    meta = ds.read_meta("000001")
    assert meta["source_image"] == "p1.png" and len(meta["shelf_heights_m"]) == 3
    # each level's span across the photo, for placement supervision: the frontal camera's view of
    # the 2 m rack at 3.2 m (f = 520 px on a 640-px photo) spans 325 px, centred
    spans = ds.read_level_spans("000001", 4)
    np.testing.assert_allclose(spans[:3], [[0.5 - 325 / 1280, 0.5 + 325 / 1280]] * 3, atol=1e-3)
    assert np.isnan(spans[3]).all()
    # same seed, same split; a non-empty output folder is refused
    rc = annotate_main(["export", str(proj.root), "--out", str(out)])
    assert rc == 2 and "not empty" in capsys.readouterr().err
    # an annotation whose photo left the project cannot be exported, but it is named, not silent
    (proj.root / "p0.png").unlink()
    assert annotate_main(["export", str(proj.root), "--out", str(tmp_path / "ds2")]) == 0
    printed = capsys.readouterr().out
    assert "exported 2 image(s)" in printed
    assert "1 annotation file(s) whose photo is no longer in the project" in printed and "p0.png.json" in printed


def test_export_refuses_incomplete_and_bad_split(tmp_path, capsys):
    proj = make_project(tmp_path, 2)
    ann = proj.load("p1.png")
    ann["rack"]["corners"] = ann["rack"]["corners"][:3]
    proj.save(ann)
    rc = annotate_main(["export", str(proj.root), "--out", str(tmp_path / "o1")])
    err = capsys.readouterr().err
    assert rc == 2 and "p1.png.json: cannot export (3 of 4 rack corners set)" in err
    assert not (tmp_path / "o1").exists()
    rc = annotate_main(["export", str(proj.root), "--out", str(tmp_path / "o2"), "--only-status", "todo", "--split", "train=5"])
    assert rc == 2 and "no annotation with status todo" in capsys.readouterr().err
    with pytest.raises(ValueError, match="asks for 5 images but 2"):
        split_ids(["a", "b"], counts={"train": 5})
    # a rack size no rack has (1e-9 typed for 1) is refused by name, as it is in the tool
    from annotate.editor import Tool

    (tmp_path / "two").mkdir()
    two = make_project(tmp_path / "two", 2)
    ann = two.load("p0.png")
    ann["rack"]["height"] = 1e-9
    (two.root / "annotations" / "p0.png.json").write_text(json.dumps(ann))
    rc = annotate_main(["export", str(two.root), "--out", str(tmp_path / "o4")])
    assert rc == 2 and "p0.png.json: cannot export (rack height 1e-09 m is not a rack's size (0.05 to 100 m))" \
        in capsys.readouterr().err
    tool = Tool(two)
    assert tool.set_rack(tool.open("p1.png"), width=0.001).msg == "⚠ rack width must be between 0.05 and 100 m"
    ann["rack"]["height"] = 1.9
    (two.root / "annotations" / "p0.png.json").write_text(json.dumps(ann))
    # counts that leave images in no split (never trained or tested on) are refused, not silent
    rc = annotate_main(["export", str(two.root), "--out", str(tmp_path / "o3"),
                        "--split", "train=1"])
    err = capsys.readouterr().err
    assert rc == 2 and "gives a split to 1 of the 2 exported images" in err and not (tmp_path / "o3").exists()


def test_photo_names_as_cameras_and_people_write_them_are_labelled_and_exported(tmp_path, capsys):
    """A copied photo ('IMG_0001 (1).png'), a name in another language, spaces: the project lists,
    opens, saves and exports them (they used to stop `serve` and the whole project's export)."""
    from annotate.editor import Tool

    names = ["IMG_0001 (1).png", "Regal Übersicht.png", "倉庫 #2.png"]
    proj = make_project(tmp_path, 3, names=names)
    assert proj.images() == sorted(names)
    tool = Tool(proj)
    st = tool.open("Regal Übersicht.png")
    assert tool.frame(st) is not None and proj.load("Regal Übersicht.png")["image"] == "Regal Übersicht.png"
    out = tmp_path / "ds"
    assert annotate_main(["export", str(proj.root), "--out", str(out), "--split", "train=2,test=1"]) == 0
    assert check_dataset(out).ok
    got = sorted(RackLayRoot(out).read_meta(f"{k:06d}")["source_image"] for k in range(3))
    assert got == sorted(names)
    # what is still refused is what a project cannot store: a path, a hidden file, an invisible
    # character; each a one-line error that names the file and says to rename it
    for bad in ("a/b.png", ".x.png", "zero\u200bwidth.png", "bell\x07.png", " lead.png"):
        with pytest.raises(ValueError, match="not a plain file name.*rename the photo"):
            proj.image_path(bad)
    (proj.root / "tab\tname.png").write_bytes((proj.root / names[0]).read_bytes())
    assert annotate_main(["export", str(proj.root), "--out", str(tmp_path / "ds2")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'tab\\tname.png'" in err and "rename the photo" in err


def test_import_round_trip(tmp_path, capsys):
    proj = make_project(tmp_path, 2)
    out = tmp_path / "ds"
    assert annotate_main(["export", str(proj.root), "--out", str(out), "--split-fractions", "train=0.5,test=0.5"]) == 0
    rev = tmp_path / "review"
    assert annotate_main(["import", str(out), str(rev)]) == 0
    p2 = Project(rev)
    assert p2.images() == ["ds_000000.png", "ds_000001.png"]
    assert (p2.settings["R"], p2.settings["D"]) == (4, 256)
    ann = p2.load("ds_000000.png")
    assert ann["status"] == "needs review"
    lay = p2.read_imported(ann)
    np.testing.assert_array_equal(lay["front"], RackLayRoot(out).read_layouts("front", "000000"))
    # the tool shows the imported layouts read-only beside the photo, and over it once the
    # rack and shelves are marked
    from annotate import draw as D
    from annotate.editor import Tool
    tool = Tool(p2)
    st = tool.open("ds_000000.png")
    pv = D.preview(tool.frame(st))
    assert pv is not None and pv.shape[0] > 2 * 150
    src = proj.load("p0.png")
    st = tool.act(st, lambda a: a.update(rack=src["rack"], shelves=src["shelves"]))
    assert any(sh["c"] == D.hex_colour(D.C_IMPORT) for sh in D.overlay(tool.frame(st)))  # imported boxes outlined
    assert proj.load("p0.png")["boxes"]  # (source project untouched)
    assert annotate_main(["import", str(out), str(rev)]) == 2
    assert "already in the project" in capsys.readouterr().err


def tree(path):
    """Every file and folder under `path` (relative), to show that a refused command wrote nothing."""
    return sorted(str(p.relative_to(path)) for p in path.rglob("*")) if path.exists() else None


def one_line_error(capsys):
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_export_unreadable_photo_writes_nothing(tmp_path, capsys):
    proj = make_project(tmp_path, 4)
    good = (proj.root / "p2.png").read_bytes()
    (proj.root / "p2.png").write_text("not a photo\n")  # the 3rd photo
    before = tree(tmp_path)
    out = tmp_path / "ds"
    rc = annotate_main(["export", str(proj.root), "--out", str(out)])
    err = one_line_error(capsys)
    assert rc == 2 and "p2.png: not a readable image" in err
    assert tree(tmp_path) == before  # no dataset, no temporary folder beside it
    # an empty --out folder stays empty on failure and is filled on success
    out.mkdir()
    assert annotate_main(["export", str(proj.root), "--out", str(out)]) == 2
    one_line_error(capsys)
    assert tree(out) == []
    (proj.root / "p2.png").write_bytes(good)
    assert annotate_main(["export", str(proj.root), "--out", str(out)]) == 0
    rep = check_dataset(out)
    assert rep.ok and rep.samples == 4 and rep.splits == {"train": 3, "test": 1}, rep.problems
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "proj"]


def test_export_split_fractions_must_sum_to_one(tmp_path, capsys):
    proj = make_project(tmp_path, 2)
    out = tmp_path / "ds"
    rc = annotate_main(["export", str(proj.root), "--out", str(out), "--split-fractions", "train=0.5,test=0.2"])
    err = one_line_error(capsys)
    assert rc == 2 and "--split-fractions" in err and "sum to 0.7" in err
    assert not out.exists()
    rc = annotate_main(["export", str(proj.root), "--out", str(out), "--split-fractions", "train=0.7,val=0.1,test=0.2"])
    assert rc == 0 and check_dataset(out).splits == {"train": 1, "val": 0, "test": 1}


def test_export_split_file_puts_each_photo_in_its_split(tmp_path, capsys):
    """--split-file (e.g. SOURCES.tsv with a split chosen by site): each photo goes to the split its
    row names, whatever the shuffle; a photo without a row, a row naming no photo of the project or
    a file without the columns stops the export with one line, and nothing is written."""
    proj = make_project(tmp_path, 4)
    tsv = tmp_path / "SOURCES.tsv"
    tsv.write_text("file\tsite\tsplit\np0.png\ta\ttest\np1.png\tb\ttrain\np2.png\ta\ttest\np3.png\tc\ttrain\n")
    out = tmp_path / "ds"
    assert annotate_main(["export", str(proj.root), "--out", str(out), "--split-file", str(tsv)]) == 0
    assert "splits: test=2, train=2" in capsys.readouterr().out
    ds = RackLayRoot(out)
    assert {ds.read_meta(s)["source_image"] for s in ds.resolve("test")} == {"p0.png", "p2.png"}
    assert check_dataset(out).ok
    for text, why in (("file\tsplit\np0.png\ttest\np1.png\ttrain\n", "no split for 2 exported photo(s) (first: p2.png)"),
                      ("file\tsplit\np0.png\ttest\np1.png\ttrain\np2.png\ttest\np3.png\ttrain\nzz.png\ttest\n",
                       "not in"),
                      ("file\tsite\np0.png\ta\n", "no 'split' column"),
                      ("file\tsplit\np0.png\ttest\np0.png\ttrain\n", "line 3: p0.png is listed twice"),
                      # a split name is a plain word: never a path out of the dataset
                      ("file\tsplit\np0.png\ttest\np1.png\ttrain\np2.png\t../../evil\np3.png\ttrain\n",
                       "line 4: split name '../../evil': use letters, digits")):
        tsv.write_text(text)
        bad = tmp_path / "bad"
        assert annotate_main(["export", str(proj.root), "--out", str(bad), "--split-file", str(tsv)]) == 2
        err = capsys.readouterr().err.strip()
        assert why in err and len(err.splitlines()) == 1, err
        assert not bad.exists() and not list(tmp_path.glob(".bad.*"))
    assert not list(tmp_path.parent.parent.glob("evil*"))
    # a split file saved by a spreadsheet (byte-order mark) reads as any other
    tsv.write_bytes("\ufefffile\tsplit\np0.png\ttest\np1.png\ttrain\np2.png\ttest\np3.png\ttrain\n".encode())
    assert annotate_main(["export", str(proj.root), "--out", str(tmp_path / "bom"), "--split-file", str(tsv)]) == 0


def exported(tmp_path, n=5):
    proj = make_project(tmp_path, n)
    out = tmp_path / "ds"
    assert annotate_main(["export", str(proj.root), "--out", str(out), "--split", f"train={n}"]) == 0
    return out


@pytest.mark.parametrize("bad", ["corrupt", "shape", "first top"])
def test_import_bad_layout_imports_nothing(tmp_path, capsys, bad):
    """The bad file is the one named: also when it is the first sample's top layout (whose good
    front layout was blamed before, being read against the bad file's shape)."""
    out = exported(tmp_path)
    capsys.readouterr()
    f = out / "frontLayouts" / "front000003.npy"  # the 4th sample
    if bad == "first top":
        f = out / "topLayouts" / "top000000.npy"
    good = f.read_bytes()
    if bad == "corrupt":
        f.write_bytes(good[:100])
    else:
        np.save(f, np.load(f)[:2])  # 2 shelves where the others have 4
    rev = tmp_path / "review"
    rc = annotate_main(["import", str(out), str(rev)])
    err = one_line_error(capsys)
    assert rc == 2 and f"{f}:" in err
    assert not rev.exists()  # the project was not even created
    # an existing project is left exactly as it was
    Project(rev)
    before = tree(rev)
    assert annotate_main(["import", str(out), str(rev)]) == 2
    assert f"{f}:" in one_line_error(capsys) and tree(rev) == before
    f.write_bytes(good)  # fixed: the retry imports every sample
    assert annotate_main(["import", str(out), str(rev)]) == 0
    assert "imported 5 image(s)" in capsys.readouterr().out
    assert Project(rev).images() == [f"ds_00000{k}.png" for k in range(5)]


def test_import_refuses_layouts_without_photo(tmp_path, capsys):
    out = exported(tmp_path)
    capsys.readouterr()
    (out / "Images" / "000002.png").unlink()
    rev = tmp_path / "review"
    rc = annotate_main(["import", str(out), str(rev)])
    err = one_line_error(capsys)
    assert rc == 2 and f"{out / 'Images' / '000002.png'}: image file not found" in err
    assert "top000002.npy" in err
    assert not rev.exists()
    # the same through a split file that lists the sample
    rc = annotate_main(["import", str(out), str(rev), "--split", "train"])
    assert rc == 2 and f"{out / 'Images' / '000002.png'}: image file not found" in one_line_error(capsys)
    assert not rev.exists()


def test_import_write_failure_rolls_back(tmp_path, capsys, monkeypatch):
    out = exported(tmp_path)
    rev = tmp_path / "review"
    proj = Project(rev)
    before, settings = tree(rev), dict(proj.settings)
    real_save, calls = Project.save, []

    def save(self, ann, user=None):  # the disk fills up at the 3rd sample
        calls.append(ann["image"])
        if len(calls) == 3:
            raise OSError(28, "No space left on device", str(self.annotation_path(ann["image"])))
        return real_save(self, ann, user)

    monkeypatch.setattr(Project, "save", save)
    with pytest.raises(OSError):
        from annotate.dataset import import_dataset
        import_dataset(out, proj)
    assert calls[2] == "ds_000002.png" and tree(rev) == before
    assert Project(rev).settings == settings


def _edit(proj, name, fn):
    """Change an annotation file behind the tool's back (a hand edit, a bad script)."""
    p = proj.annotation_path(name)
    ann = json.loads(p.read_text())
    fn(ann)
    p.write_text(json.dumps(ann))
    return p


def test_export_refuses_annotations_that_do_not_fit_their_photo(tmp_path, capsys):
    """Absurd annotations exported silently before (phantom shelf channels, shifted channels,
    dropped boxes): now they stop the export with one line naming every bad file (a truncated JSON
    file among them: it used to block even --skip-invalid), --skip-invalid lists each one left out,
    and every geometry warning written to meta/ is printed."""
    proj = make_project(tmp_path, 9)
    bad = {
        "p0.png": (lambda a: a["rack"]["corners"].__setitem__(0, [1e12, -1e12]),
                   "rack corner 1 at (1e+12, -1e+12) is outside the 640x480 photo"),
        "p1.png": (lambda a: a["shelves"][0].__setitem__("point", [300.0, 480.0 * 50]),
                   "shelf 0 at (300, 24000) is outside the 640x480 photo"),
        "p2.png": (lambda a: a["shelves"][1].__setitem__("point", [300.0, 6.5e299]),
                   "shelf 1 at (300, 6.5e+299) is outside the 640x480 photo"),
        "p3.png": (lambda a: a["boxes"][0].__setitem__("p1", list(a["boxes"][0]["p0"])),
                   "box 0 has no area (0 x 0 px)"),
        "p4.png": (lambda a: a["boxes"][1].update(p0=[700.0, 500.0], p1=[800.0, 600.0]),
                   "box 1 corner p0 at (700, 500) is outside the 640x480 photo; and 1 more"),
        "p5.png": (lambda a: a.__setitem__("image_size", [1280, 960]),
                   "field 'image_size' says 1280x960, but the photo is 640x480 pixels"),
        "p6.png": (lambda a: a.__setitem__("image", "p7.png"),
                   "field 'image' says 'p7.png', but the photo is 'p6.png'"),
    }
    paths = {name: _edit(proj, name, fn) for name, (fn, _) in bad.items()}
    # p7 is fine but a box sticks out of the rack's depth: a warning, written to meta/ and printed
    _edit(proj, "p7.png", lambda a: a["boxes"][0].update(front_offset=0.5, depth=0.5))
    truncated = proj.annotation_path("p8.png")
    truncated.write_text(truncated.read_text()[:40])
    out = tmp_path / "ds"
    rc = annotate_main(["export", str(proj.root), "--out", str(out)])
    err = one_line_error(capsys)
    assert rc == 2 and "8 annotations cannot be exported" in err, err
    for name, (_, why) in bad.items():
        assert f"{paths[name]}: cannot export ({why})" in err, (name, err)
    assert str(truncated) in err
    assert not out.exists()
    rc = annotate_main(["export", str(proj.root), "--out", str(out), "--skip-invalid"])
    cap = capsys.readouterr()
    assert rc == 0 and "exported 1 image(s)" in cap.out and "skipped 8 invalid annotation(s)" in cap.out
    lines = cap.err.splitlines()
    assert any(line.startswith(f"annotate export: skipped: {truncated}") for line in lines), lines
    for name, (_, why) in bad.items():
        assert f"annotate export: skipped: {paths[name]}: cannot export ({why})" in lines, (name, lines)
    warned = [l for l in lines if "warning" in l]
    meta = RackLayRoot(out).read_meta("000000")
    assert meta["source_image"] == "p7.png" and meta["warnings"]
    assert warned == [f"annotate export: warning: p7.png: {w}" for w in meta["warnings"]]
    assert check_dataset(out).ok


def test_server_refuses_edits_that_leave_the_photo_but_saves_fixes(tmp_path):
    """The same check guards saving: an edit that puts a point outside the photo or makes a box
    without area is refused with one line; a file that is already bad can be fixed item by item."""
    from annotate import schema as S

    proj = make_project(tmp_path, 1)
    ann = proj.load("p0.png")
    ann["boxes"][0]["p1"] = [5000.0, 10.0]
    with pytest.raises(S.SchemaError, match=r"p0\.png\.json: box 0 corner p1 at \(5000, 10\) is outside the "
                                            r"640x480 photo"):
        proj.save(ann)
    ann = proj.load("p0.png")
    ann["boxes"][1]["p0"] = list(ann["boxes"][1]["p1"])
    with pytest.raises(S.SchemaError, match="box 1 has no area"):
        proj.save(ann)
    # a file broken by hand in two places: removing one problem saves, adding one does not
    _edit(proj, "p0.png", lambda a: (a["boxes"][0].__setitem__("p0", [-900.0, 0.0]),
                                     a["boxes"][1].__setitem__("p0", [-900.0, 0.0])))
    ann = proj.load("p0.png")
    ann["boxes"] = [b for b in ann["boxes"] if b["id"] != 0]
    assert proj.save(ann)["version"] == ann["version"] + 1
    ann = proj.load("p0.png")
    ann["shelves"][0]["point"] = [10.0, 9000.0]
    with pytest.raises(S.SchemaError, match="shelf 0 at"):
        proj.save(ann)
