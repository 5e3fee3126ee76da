"""Decompression bombs: a real 30000 x 30000 PNG (under 1 MB on disk, 0.9 G pixels) is refused by
every command that reads photos, from its header, with one line naming the file, in little
memory, and nothing half-written is left behind. Each command runs in its own process so its
peak memory (ru_maxrss of that child) and CPU time can be measured."""
from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from racklay.data import DataError, image_info, read_image
from racklay.toy import build_toy_dataset

BOMB_SIDE = 30000


def write_png_bomb(path: Path, w: int, h: int) -> Path:
    """A real, valid w x h 8-bit grey PNG of zeros, built without compressing w*h bytes: a block
    of zero rows is compressed once, ending in a full flush (which resets the compressor, so the
    block's compressed bytes are the same every time), and that block is repeated; the zlib
    checksum is computed over the true data, so every decoder accepts the file."""
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xffffffff)

    rows = 200
    block = bytes(w + 1) * rows          # each row: filter byte 0 + w zero pixels
    z = zlib.compressobj(9)
    head = z.compress(block) + z.flush(zlib.Z_FULL_FLUSH)
    rep = z.compress(block) + z.flush(zlib.Z_FULL_FLUSH)
    n, rest = divmod(h, rows)
    tail = z.compress(bytes(w + 1) * rest) + z.flush()[:-4]   # drop the checksum of what z saw
    adler = 1
    for _ in range(n):
        adler = zlib.adler32(block, adler)
    adler = zlib.adler32(bytes(w + 1) * rest, adler)
    idat = head + rep * (n - 1) + tail + struct.pack(">I", adler)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", idat) + chunk(b"IEND", b""))
    return path


def test_bomb_builder_makes_a_real_png(tmp_path):
    import cv2

    p = write_png_bomb(tmp_path / "small.png", 301, 457)
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    assert img.shape == (457, 301) and img.max() == 0
    assert read_image(p).shape == (457, 301, 3)


def test_limit_from_header_and_env(tmp_path, monkeypatch):
    p = write_png_bomb(tmp_path / "eight.png", 4000, 2000)          # 8 Mpx
    assert image_info(p).width == 4000
    monkeypatch.setenv("RACKLAY_MAX_MEGAPIXELS", "5")
    with pytest.raises(DataError, match=r"eight\.png: 4000x2000 pixels \(8 Mpx\) is over the 5 Mpx limit.*"
                                        r"RACKLAY_MAX_MEGAPIXELS"):
        read_image(p)
    monkeypatch.setenv("RACKLAY_MAX_MEGAPIXELS", "lots")
    with pytest.raises(DataError, match="RACKLAY_MAX_MEGAPIXELS='lots'"):
        read_image(p)
    monkeypatch.setenv("RACKLAY_MAX_MEGAPIXELS", "9")
    assert read_image(p).shape == (2000, 4000, 3)


@pytest.fixture(scope="module")
def bomb_setup(tmp_path_factory):
    import torch

    from annotate.store import Project
    from racklay.checkpoint import save_checkpoint
    from racklay.model import ModelConfig, RackLayNet

    base = tmp_path_factory.mktemp("bombs")
    bomb = write_png_bomb(base / "bomb.png", BOMB_SIDE, BOMB_SIDE)
    assert bomb.stat().st_size < 2 * 2**20
    # a toy dataset whose first image (in every split that lists it) is the bomb
    ds = build_toy_dataset(base / "toy", n=8, seed=0, R=4, D=64)
    sid = ds.ids()[0]
    shutil.copy(bomb, ds.image_path(sid))
    torch.manual_seed(0)
    cfg = ModelConfig(R=4, image_size=64, layout_size=32)
    weights = save_checkpoint(base / "w.safetensors", RackLayNet(cfg), cfg)
    # an annotation project whose one finished photo is the bomb
    proj = Project(base / "proj")
    from annotate.schema import new_annotation

    shutil.copy(bomb, proj.root / "big.png")
    ann = new_annotation("big.png", BOMB_SIDE, BOMB_SIDE)
    ann.update(status="done", version=1)
    proj.annotation_path("big.png").parent.mkdir()
    proj.annotation_path("big.png").write_text(json.dumps(ann))   # (the server refuses to save it)
    split = next(s for s in ds.splits() if sid in ds.split_ids(s))
    return dict(base=base, bomb=bomb, ds=ds, sid=sid, split=split, weights=weights, proj=proj.root)


# A child's ru_maxrss starts at its parent's RSS at fork time (Linux keeps the high-water mark
# across exec), so the command is started from a small launcher, not from this (torch-sized)
# process; the launcher reports its child's peak RSS (KB) and CPU seconds.
_LAUNCHER = """
import os, subprocess, sys, time
t = time.monotonic()
p = subprocess.Popen(sys.argv[2:])
_, status, ru = os.wait4(p.pid, 0)
open(sys.argv[1], "w").write(f"{ru.ru_maxrss} {ru.ru_utime + ru.ru_stime} {time.monotonic() - t}")
sys.exit(os.waitstatus_to_exitcode(status) & 255)
"""


def _run(args: list[str], log: Path) -> tuple[int, str, float, float, float]:
    """Run `python -m ...` in a child process; -> (exit code, stderr, peak RSS in MB, CPU seconds,
    wall seconds)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "GRADIO_ANALYTICS_ENABLED": "False"}
    env.pop("RACKLAY_MAX_MEGAPIXELS", None)
    stats = log.with_suffix(".rusage")
    with open(log, "w") as out, open(log.with_suffix(".err"), "w") as err:
        rc = subprocess.run([sys.executable, "-c", _LAUNCHER, str(stats), sys.executable, "-m", *args],
                            stdout=out, stderr=err, env=env, timeout=600).returncode
    kb, cpu, wall = stats.read_text().split()
    return rc, log.with_suffix(".err").read_text(), int(kb) / 1024, float(cpu), float(wall)


@pytest.mark.slow
def test_every_command_refuses_a_real_30000px_png(bomb_setup, tmp_path):
    b = bomb_setup
    ds, sid, w = b["ds"], b["sid"], str(b["weights"])
    img = str(ds.image_path(sid))
    cases = {
        "check-data": (["racklay", "check-data", str(ds.root)], img, None),
        "show": (["racklay", "show", str(ds.root), "--id", sid, "--out", str(tmp_path / "fig.png")], img,
                 tmp_path / "fig.png"),
        "train": (["racklay", "train", "--data", str(ds.root), "--out", str(tmp_path / "runs"), "--name", "r",
                   "--train-split", b["split"], "--val-split", b["split"], "--epochs", "1", "--image-size", "64",
                   "--layout-size", "32", "--batch-size", "2", "--threads", "1", "--no-progress"], img,
                  tmp_path / "runs" / "r"),
        "eval": (["racklay", "eval", "--weights", w, "--data", str(ds.root), "--split", "all", "--threads", "1"],
                 img, None),
        "predict": (["racklay", "predict", str(b["bomb"]), "--weights", w, "--out", str(tmp_path / "pred"),
                     "--threads", "1"], str(b["bomb"]), tmp_path / "pred"),
        "analyze": (["racklay", "analyze", str(b["bomb"]), "--weights", w, "--out", str(tmp_path / "an")],
                    str(b["bomb"]), None),
        "annotate import": (["annotate.cli", "import", str(ds.root), str(tmp_path / "imp")], img, tmp_path / "imp"),
        "annotate export": (["annotate.cli", "export", str(b["proj"]), "--out", str(tmp_path / "exp")],
                            str(b["proj"] / "big.png"), tmp_path / "exp"),
    }
    measured = {}
    for name, (args, named, must_not_exist) in cases.items():
        rc, err, rss_mb, cpu_s, wall_s = _run(args, tmp_path / f"{name.replace(' ', '_')}.log")
        measured[name] = (round(rss_mb), round(cpu_s, 1), round(wall_s, 1))
        out = err + (tmp_path / f"{name.replace(' ', '_')}.log").read_text()
        assert rc != 0, (name, out[-2000:])
        assert f"{named}: {BOMB_SIDE}x{BOMB_SIDE} pixels (900 Mpx) is over the 40 Mpx limit" in out, (name, out[-2000:])
        assert "Traceback" not in err, (name, err[-2000:])
        # decoding the bomb takes 2.7 GB and seconds of CPU; the header check takes neither (the
        # bounds leave room for torch's start-up on a slow machine)
        assert rss_mb < 1024, (name, rss_mb)
        assert cpu_s < 30, (name, cpu_s)
        if must_not_exist is not None:
            assert not must_not_exist.exists(), (name, sorted(must_not_exist.rglob("*")))
    print("bomb: peak RSS MB, CPU s, wall s per command:", measured)


def test_annotator_refuses_the_bomb_from_its_header(bomb_setup):
    """The annotator's server reads photos through Project.read_image / image_size: refused with
    one line before decoding (this would take 2.7 GB)."""
    import resource

    from annotate.store import Project, StoreError

    proj = Project(bomb_setup["proj"], create=False)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(StoreError, match=r"big\.png: 30000x30000 pixels .* over the 40 Mpx limit"):
        proj.read_image("big.png")
    with pytest.raises(StoreError, match="over the 40 Mpx limit"):
        proj.image_size("big.png")
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200 * 1024


def test_predict_leaves_no_half_written_sample(tmp_path, monkeypatch):
    """A prediction that fails while writing (here: the figure) leaves none of its files."""
    import racklay.viz
    from racklay.checkpoint import save_checkpoint
    from racklay.model import ModelConfig, RackLayNet
    from racklay.predict import Predictor, predict_folder

    cfg = ModelConfig(R=2, image_size=64, layout_size=32)
    w = save_checkpoint(tmp_path / "w.safetensors", RackLayNet(cfg), cfg)
    photos = tmp_path / "in"
    photos.mkdir()
    from racklay.atomic import atomic_save_png

    atomic_save_png(photos / "a.png", np.zeros((40, 50, 3), np.uint8))
    atomic_save_png(photos / "b.png", np.zeros((40, 50, 3), np.uint8))
    real = racklay.viz.layout_figure

    def fail_on_b(image, top, front, out, **kw):
        if Path(out).stem == "b":
            raise MemoryError("Unable to allocate 10.1 GiB")
        return real(image, top, front, out=out, **kw)

    monkeypatch.setattr(racklay.viz, "layout_figure", fail_on_b)
    logged = []
    rep = predict_folder(Predictor(str(w)), [photos], tmp_path / "out", progress=False, log=logged.append)
    assert rep.done == ["a"] and len(rep.failed) == 1
    assert logged == [f"error: {photos / 'b.png'}: out of memory (Unable to allocate 10.1 GiB)"]
    left = sorted(p.relative_to(tmp_path / "out").as_posix() for p in (tmp_path / "out").rglob("*") if p.is_file())
    assert left and all("b" not in Path(p).stem for p in left), left
