import shutil

import numpy as np
import pytest
import torch

from conftest import make_toy
from racklay import layout as L
from racklay.data import DataError, RackLayRoot, check_dataset, make_splits, parse_split_entry
from racklay.torchdata import RackLayDataset


@pytest.fixture(scope="module")
def toy_root(tmp_path_factory):
    return make_toy(tmp_path_factory, n=10, seed=1, D=64)


@pytest.fixture
def ds(toy_root, tmp_path):
    dst = tmp_path / "ds"
    shutil.copytree(toy_root, dst)
    return RackLayRoot(dst)


def test_layout_on_disk_is_racklay_format(toy_root):
    ds = RackLayRoot(toy_root)
    sid = ds.ids()[0]
    assert (toy_root / "Images" / f"{sid}.png").is_file()
    raw = np.load(toy_root / "topLayouts" / f"top{sid}.npy")
    assert raw.dtype == np.uint8 and raw.shape == (4, 64, 64)
    assert set(np.unique(raw)) <= {0, 115, 255}
    assert set(ds.splits()) == {"train", "val", "test"}
    assert sum(len(ds.split_ids(s)) for s in ds.splits()) == 10
    assert check_dataset(toy_root).ok


def test_split_entries_accept_paths_and_ids():
    assert parse_split_entry("Images/000123.png") == "000123"
    assert parse_split_entry("/home/u/RackLay/data/Images/000123.png\n") == "000123"
    assert parse_split_entry("000123") == "000123"
    assert parse_split_entry("C:\\data\\Images\\000009.jpg") == "000009"


def test_make_splits_reproducible_and_disjoint():
    ids = [f"{i:06d}" for i in range(100)]
    a = make_splits(ids, {"train": 0.8, "val": 0.1, "test": 0.1}, seed=3)
    b = make_splits(ids, {"train": 0.8, "val": 0.1, "test": 0.1}, seed=3)
    assert a == b
    assert [len(a[k]) for k in ("train", "val", "test")] == [80, 10, 10]
    assert not set(a["train"]) & set(a["test"])


def test_make_splits_by_counts_cuts_the_same_shuffle():
    """Exact counts (annotate export --split) cut the same shuffle as fractions; what is not
    asked for is left out; impossible counts are refused."""
    ids = [f"{i:06d}" for i in range(100)]
    by_frac = make_splits(ids, {"train": 0.8, "val": 0.1, "test": 0.1}, seed=3)
    assert make_splits(ids, counts={"train": 80, "val": 10, "test": 10}, seed=3) == by_frac
    part = make_splits(ids, counts={"a": 7, "b": 3}, seed=5)
    assert [len(part["a"]), len(part["b"])] == [7, 3] and not set(part["a"]) & set(part["b"])
    assert part == make_splits(ids, {"a": 0.07, "b": 0.03}, seed=5)
    with pytest.raises(ValueError, match="ask for 101 ids but there are 100"):
        make_splits(ids, counts={"train": 101})
    with pytest.raises(ValueError, match="whole numbers"):
        make_splits(ids, counts={"train": 2.5})
    with pytest.raises(ValueError, match="either"):
        make_splits(ids, {"train": 1.0}, counts={"train": 1})


def _problems(root):
    rep = check_dataset(root)
    assert not rep.ok
    return rep.problems


def test_check_truncated_png(ds):
    p = ds.image_path(ds.ids()[0])
    p.write_bytes(p.read_bytes()[:200])
    probs = _problems(ds.root)
    assert len(probs) == 1 and str(p) in probs[0] and ("truncated" in probs[0] or "readable" in probs[0])


def test_check_wrong_shape(ds):
    sid = ds.ids()[1]
    np.save(ds.layout_path("top", sid), np.zeros((4, 64, 32), np.uint8))
    (line,) = _problems(ds.root)
    assert f"top{sid}.npy" in line and "shape" in line


def test_check_wrong_dtype(ds):
    sid = ds.ids()[2]
    np.save(ds.layout_path("front", sid), np.zeros((4, 64, 64), np.float32))
    (line,) = _problems(ds.root)
    assert f"front{sid}.npy" in line and "dtype" in line


def test_check_stray_value(ds):
    sid = ds.ids()[3]
    a = np.load(ds.layout_path("top", sid))
    a[0, 0, 0] = 114
    np.save(ds.layout_path("top", sid), a)
    (line,) = _problems(ds.root)
    assert f"top{sid}.npy" in line and "114" in line


def test_check_missing_pair_and_orphan_layout(ds):
    sid = ds.ids()[4]
    ds.layout_path("front", sid).unlink()
    (line,) = _problems(ds.root)
    assert f"front{sid}.npy" in line and "missing" in line
    orphan = ds.layout_path("top", "999999")
    shutil.copy(ds.layout_path("top", sid), orphan)
    assert any("999999" in p and "no image" in p for p in _problems(ds.root))


def test_check_in_worker_processes_gives_the_serial_report(ds):
    """`racklay check-data --workers N` and a training run with DataLoader workers check samples
    in N processes: the same problems in the same order, the same sizes and passed files."""
    from racklay.data import check_samples

    ids = ds.ids()
    ds.image_path(ids[1]).write_bytes(ds.image_path(ids[1]).read_bytes()[:200])
    ds.layout_path("front", ids[4]).unlink()
    np.save(ds.layout_path("top", ids[7]), np.zeros((4, 64, 32), np.uint8))
    a = ds.layout_path("top", ids[8])
    arr = np.load(a)
    arr[0, 0, 0] = 114
    np.save(a, arr)
    reports = []
    for workers in (0, 2):
        passed, sizes = {}, {}
        problems, common = check_samples(ds.root, ids, ("top", "front"), passed=passed, sizes=sizes, workers=workers)
        reports.append((problems, common, passed, sizes))
    assert reports[0] == reports[1]
    problems = reports[0][0]
    assert [next(k for k, m in enumerate(problems) if ids[i] in m) for i in (1, 4, 7, 8)] == [0, 1, 2, 3]
    assert check_dataset(ds.root, workers=2).problems == check_dataset(ds.root).problems


def test_check_split_to_missing_file_and_duplicates(ds):
    sp = ds.split_path("test")
    sp.write_text(sp.read_text() + "Images/424242.png\n")
    (line,) = _problems(ds.root)
    assert "test.txt" in line and "424242" in line
    first = sp.read_text().splitlines()[0]
    sp.write_text(sp.read_text() + first + "\n")
    assert any("listed 2 times" in p for p in _problems(ds.root))


def test_check_overlapping_splits(ds):
    sid = ds.split_ids("train")[0]
    sp = ds.split_path("test")
    sp.write_text(sp.read_text() + f"Images/{sid}.png\n")
    assert any("also in split" in p for p in _problems(ds.root))


def test_read_errors_name_the_file(ds, tmp_path):
    bad = tmp_path / "x.npy"
    bad.write_bytes(b"not numpy")
    from racklay.data import read_layout_file
    with pytest.raises(DataError, match="x.npy"):
        read_layout_file(bad)
    with pytest.raises(DataError, match="splits found"):
        ds.split_ids("nosuch")


def test_write_sample_encodes_and_is_atomic(tmp_path):
    ds = RackLayRoot(tmp_path / "w")
    top = np.zeros((4, 16, 16), np.uint8)
    top[0, 4:8, 4:8] = L.BOX
    ds.write_sample("000000", image=np.zeros((10, 12, 3), np.uint8), top=top, meta={"a": 1})
    assert np.load(ds.layout_path("top", "000000")).max() == 255
    np.testing.assert_array_equal(ds.read_layouts("top", "000000"), top)
    assert ds.read_meta("000000") == {"a": 1}
    assert not list((tmp_path / "w").rglob("*.tmp"))
    with pytest.raises(L.LayoutError):
        ds.write_sample("000001", top=np.full((4, 16, 16), 7, np.uint8))


def test_torch_dataset_sizes_and_values(toy_root):
    d = RackLayDataset(toy_root, split="train", image_size=(48, 80), layout_size=32, cache=True)
    item = d[0]
    assert item["image"].shape == (3, 48, 80) and item["image"].dtype == torch.float32
    assert item["top"].shape == (4, 32, 32) and item["top"].dtype == torch.uint8
    assert set(item["front"].unique().tolist()) <= {0, 1, 2}
    assert len(d) == len(RackLayRoot(toy_root).split_ids("train"))


def test_torch_dataset_transform_hook(toy_root):
    def flip(img, lays):
        return img[:, ::-1], {v: L.hflip_layouts(a) for v, a in lays.items()}

    plain = RackLayDataset(toy_root, split="val", layout_size=32, image_size=32)
    flipped = RackLayDataset(toy_root, split="val", layout_size=32, image_size=32, transform=flip)
    torch.testing.assert_close(flipped[0]["top"], plain[0]["top"].flip(-1))
    torch.testing.assert_close(flipped[0]["image"], plain[0]["image"].flip(-1))


def test_atomic_writes_get_normal_file_permissions(tmp_path):
    """Teammates must be able to read a dataset or project we wrote: atomic writes use mkstemp
    (mode 0600) internally but the final file gets 0666 minus the umask, like open() would."""
    import os
    import stat

    from racklay.atomic import atomic_write_text

    old = os.umask(0o022)
    try:
        import importlib

        import racklay.atomic as A
        importlib.reload(A)
        A.atomic_write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
        importlib.reload(A)
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644
    assert atomic_write_text  # the module-level import stays usable


@pytest.mark.parametrize("orientation", range(1, 9))
def test_phone_photos_with_exif_orientation_read_upright_everywhere(tmp_path, orientation):
    """A JPEG with an EXIF orientation (5-8: the usual portrait phone photo, stored sideways) reads
    as it is shown: the pixels PIL's exif_transpose gives, the header size turned to match, and
    the annotator's project reports that size."""
    from PIL import Image, ImageOps

    from annotate.store import Project
    from racklay.data import image_info, read_image

    stored = np.zeros((48, 64, 3), np.uint8)
    stored[:12, :, 0] = 255                        # a red band along the stored top edge
    exif = Image.Exif()
    exif[0x0112] = orientation
    path = tmp_path / "phone.jpg"
    Image.fromarray(stored).save(path, exif=exif.tobytes(), quality=95)
    got = read_image(path)
    want = np.asarray(ImageOps.exif_transpose(Image.open(path)).convert("RGB"))
    assert got.shape == want.shape == ((64, 48, 3) if orientation >= 5 else (48, 64, 3))
    assert np.abs(got.astype(int) - want).mean() < 1
    info = image_info(path)
    assert (info.width, info.height, info.orientation) == (got.shape[1], got.shape[0], orientation)
    assert Project(tmp_path).image_size("phone.jpg") == (got.shape[1], got.shape[0])


def test_npy_bytes_are_what_np_save_writes(tmp_path):
    """racklay.atomic.npy_bytes builds the .npy bytes in one piece; readers (numpy, WareSynth's own
    tools) must see exactly np.save's file."""
    import io

    from racklay.atomic import atomic_save_npy, npy_bytes

    rng = np.random.default_rng(0)
    arrays = [rng.integers(0, 3, (4, 32, 32), dtype=np.uint8), rng.random((3, 5)).astype(np.float32),
              np.zeros((0, 7), np.int64), np.arange(6, dtype=np.uint16).reshape(2, 3)[:, ::-1],
              np.array(3.5), np.zeros((2, 2), dtype=[("a", "<f4"), ("b", "u1")])]
    for a in arrays:
        ref = io.BytesIO()
        np.save(ref, a, allow_pickle=False)
        assert npy_bytes(a) == ref.getvalue(), a.dtype
        p = atomic_save_npy(tmp_path / "a.npy", a, fsync=False)
        assert np.array_equal(np.load(p), a)
    with pytest.raises(ValueError):
        npy_bytes(np.array([{"x": 1}], dtype=object))


@pytest.mark.parametrize("row_filter", ["sub", "up", None])
def test_png_files_decode_to_the_written_pixels_in_every_reader(row_filter):
    """WareSynth's PNGs (one row filter, its own deflate) and the adaptive ones must read back
    exactly, 8- and 16-bit, grey and RGB, with OpenCV (the loaders) and Pillow (the annotator)."""
    import io

    import cv2
    from PIL import Image

    from racklay.atomic import encode_png

    rng = np.random.default_rng(1)
    arrays = [rng.integers(0, 256, (37, 53, 3), dtype=np.uint8), rng.integers(0, 256, (9, 4), dtype=np.uint8),
              rng.integers(0, 65536, (21, 17), dtype=np.uint16), np.full((1, 1, 3), 200, np.uint8),
              np.arange(12, dtype=np.uint16).reshape(3, 4)[:, ::-1]]   # a view, not contiguous
    for a in arrays:
        data = encode_png(a, row_filter)
        back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if a.ndim == 3:
            back = cv2.cvtColor(back, cv2.COLOR_BGR2RGB)
        assert back.dtype == a.dtype and np.array_equal(back, a), (a.dtype, a.shape)
        assert np.array_equal(np.asarray(Image.open(io.BytesIO(data))).astype(a.dtype), a)
    for bad in (np.zeros((4, 4), np.float32), np.zeros((4, 4, 4), np.uint8), np.zeros((0, 3), np.uint8)):
        with pytest.raises(ValueError, match="encode_png"):
            encode_png(bad, row_filter)
    if row_filter:
        with pytest.raises(ValueError, match="row_filter"):
            encode_png(arrays[0], "paeth")


def test_level_spans_are_read_strictly_from_the_meta(tmp_path):
    """A sample's level spans (placement supervision): the first R levels' [left, right] from
    meta/level_spans, NaN for a level without one or a sample without meta; a malformed entry is
    one error naming the meta file and the entry, never a silently skipped level."""
    ds = RackLayRoot(tmp_path / "ds")
    ds.write_sample("a", meta={"level_spans": [[0.1, 0.9], None, [-0.2, 1.3], [0.3, 0.7], [0.0, 1.0]]})
    sp = ds.read_level_spans("a", 4)
    assert sp.shape == (4, 2) and sp.dtype == np.float32
    np.testing.assert_allclose(sp[[0, 2, 3]], [[0.1, 0.9], [-0.2, 1.3], [0.3, 0.7]])
    assert np.isnan(sp[1]).all()
    assert np.isnan(ds.read_level_spans("none", 4)).all()
    for bad, what in (([[0.9, 0.1]], r"level_spans\[0\]"), ([[0.1, 0.5], [0.2, "x"]], r"level_spans\[1\]"),
                      ([[0.1, float("nan")]], r"level_spans\[0\]"), ({"0": [0, 1]}, "must be a list")):
        ds.write_sample("b", meta={"level_spans": bad})
        with pytest.raises(DataError, match=what) as e:
            ds.read_level_spans("b", 4)
        assert str(ds.meta_path("b")) in str(e.value)
