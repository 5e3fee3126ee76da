"""racklay synth end to end: valid RackLay datasets, determinism (runs, workers, shards),
resume after an interruption, recipe errors before anything is written."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from racklay.cli import main as racklay_main
from racklay.data import RackLayRoot, check_dataset
from racklay.synth.generate import generate_dataset
from racklay.synth.recipe import RecipeError, load_recipe

TINY = ["image_width=160", "image_height=96", "focal_px=[110,175]", "layout_size=64", "clutter=[0,2]",
        "bays_per_side=1", "rack_rows=1"]


def tiny(name="complex", extra=()):
    return load_recipe(name, TINY + list(extra))


def files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "ds"
    generate_dataset(tiny(), 6, out, seed=3, progress=False)
    return out


def test_generated_set_is_valid_racklay(reference):
    rep = check_dataset(reference)
    assert rep.ok, rep.problems
    assert rep.samples == 6 and rep.R == 4 and rep.D == 64 and set(rep.views) == {"top", "front"}
    assert sum(rep.splits.values()) == 6
    ds = RackLayRoot(reference)
    n_items = 0
    for sid in ds.ids():
        meta = ds.read_meta(sid)
        top = ds.read_layouts("top", sid)
        n_vis = len(meta["rack"]["visible_shelves"])
        assert len(meta["shelf_heights"]) == n_vis
        # channels of visible shelves hold the shelf, the others are empty
        assert all(top[c].any() for c in range(n_vis)) and not top[n_vis:].any()
        # every item on a visible shelf sits on BOX pixels of its channel, in both views
        from racklay.layout import BOX, Grid
        g = Grid(64, 8.0)
        front = ds.read_layouts("front", sid)
        on_rack = [o for o in meta["objects"] if o["channel"] is not None]
        n_items += len(on_rack)
        for o in on_rack:
            f = o["shelf_frame"]
            col = int(g.x_to_col(f["cx"]))
            assert top[o["channel"], int(g.y_to_row(f["cy"])), col] == BOX
            assert front[o["channel"], int(g.z_to_row(f["z0"] + o["size"][2] / 2)), col] == BOX
        img = ds.read_image(sid)
        assert img.shape == (96, 160, 3)
        for extra, dtype in (("depth", np.uint16), ("instance", np.uint16), ("semantic", np.uint8), ("normals", np.uint8)):
            import cv2
            a = cv2.imread(str(reference / extra / f"{sid}.png"), cv2.IMREAD_UNCHANGED)
            assert a is not None and a.dtype == dtype and a.shape[:2] == (96, 160)
        assert (reference / "kitti" / f"{sid}.txt").exists()
    assert n_items >= 5
    coco = json.loads((reference / "annotations" / "instances_train.json").read_text())
    # ids are stable: the 6 cartons and 2 crates first, the pallet load units appended after them
    names = [c["name"] for c in coco["categories"]]
    assert names[0] == "carton_small" and names[6:8] == ["crate_blue", "crate_red"]
    assert names[8:] == ["pallet_cartons", "pallet_wrapped", "pallet_crates"]
    assert coco["images"] and coco["annotations"]


def test_cli_check_data_passes_and_proxy_real(tmp_path, capsys):
    out = tmp_path / "proxy"
    rc = racklay_main(["synth", "--recipe", "proxy_real", "--n", "3", "--out", str(out), "--seed", "1",
                       "--no-progress"] + sum((["--set", s] for s in TINY), []))
    assert rc == 0
    assert racklay_main(["check-data", str(out)]) == 0
    meta = RackLayRoot(out).read_meta("000000")
    assert meta["domain"] == "proxy-real" and meta["recipe"] == "proxy_real"


@pytest.mark.parametrize("style", ["pallet", "cube", "wire", "boltless", "slotted"])
def test_rack_style_dataset_passes_check_data(tmp_path, style):
    out = tmp_path / style
    rc = racklay_main(["synth", "--recipe", style, "--n", "3", "--out", str(out), "--seed", "2",
                       "--no-progress"] + sum((["--set", s] for s in TINY), []))
    assert rc == 0 and racklay_main(["check-data", str(out)]) == 0
    meta = RackLayRoot(out).read_meta("000000")
    assert meta["rack"]["style"] == style and meta["recipe"] == style
    if style == "pallet":
        assert "pallet" in meta["semantic_classes"]
        coco = json.loads(next((out / "annotations").glob("instances_*.json")).read_text())
        assert {"pallet_cartons", "pallet_wrapped", "pallet_crates"} <= {c["name"] for c in coco["categories"]}


def test_same_seed_same_bytes_across_runs_and_workers(tmp_path, reference):
    a = tmp_path / "again"
    generate_dataset(tiny(), 6, a, seed=3, progress=False)
    assert files(a) == files(reference)
    w = tmp_path / "workers"
    generate_dataset(tiny(), 6, w, seed=3, progress=False, workers=2)
    assert files(w) == files(reference)
    other = tmp_path / "other_seed"
    generate_dataset(tiny(), 2, other, seed=4, progress=False)
    assert (other / "Images" / "000000.png").read_bytes() != (reference / "Images" / "000000.png").read_bytes()


def test_shards_merge_into_the_full_dataset(tmp_path, reference):
    merged = tmp_path / "merged"
    for i in range(2):
        part = tmp_path / f"shard{i}"
        res = generate_dataset(tiny(), 6, part, seed=3, shard=f"{i}/2", progress=False)
        assert sorted(res.generated) == list(range(i, 6, 2))
        shutil.copytree(part, merged, dirs_exist_ok=True)
    res = generate_dataset(tiny(), 6, merged, seed=3, progress=False)  # nothing left: rebuilds splits/COCO
    assert res.generated == [] and res.skipped == 6
    assert files(merged) == files(reference)


def test_resume_after_interruption(tmp_path, reference):
    out = tmp_path / "resumed"
    generate_dataset(tiny(), 6, out, seed=3, progress=False, limit=3)  # "interrupted" after 3 images
    assert len(RackLayRoot(out).ids()) == 3
    # an index cut short mid-write: layouts written, no image and no meta yet
    ref = RackLayRoot(reference)
    (out / "topLayouts").mkdir(exist_ok=True)
    shutil.copy(ref.layout_path("top", "000004"), RackLayRoot(out).layout_path("top", "000004"))
    (out / "Images" / ".000004.png.tmp").write_bytes(b"partial")  # a temp file left by a kill
    res = generate_dataset(tiny(), 6, out, seed=3, progress=False)
    assert sorted(res.generated) == [3, 4, 5] and res.skipped == 3
    (out / "Images" / ".000004.png.tmp").unlink()
    assert files(out) == files(reference)


def test_resume_by_a_different_generator_version_is_refused(tmp_path):
    """The manifest records the generator's code fingerprint: the same seed renders other scenes
    under other code, so finishing a dataset with it would mix two generators."""
    out = tmp_path / "v1"
    generate_dataset(tiny(), 4, out, seed=3, progress=False, limit=2)
    man = json.loads((out / "waresynth.json").read_text())
    assert len(man["code"]) == 16 and man["version"]
    man["code"] = "0" * 16
    (out / "waresynth.json").write_text(json.dumps(man))
    with pytest.raises(ValueError, match="different generator version"):
        generate_dataset(tiny(), 4, out, seed=3, progress=False)
    assert len(RackLayRoot(out).ids()) == 2


def test_real_interrupt_leaves_no_partial_files(tmp_path):
    """Kill a CLI run mid-way; every listed sample is complete and a rerun finishes the set."""
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "racklay", "synth", "--recipe", "simple", "--n", "40", "--out", str(out),
           "--no-progress"] + sum((["--set", s] for s in TINY), [])
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    import time
    t0 = time.time()
    while time.time() - t0 < 60 and len(list((out / "meta").glob("*.json"))) < 2:
        time.sleep(0.1)
    proc.kill()
    proc.wait()
    ds = RackLayRoot(out)
    for sid in ds.ids():  # every image that exists is a complete PNG
        ds.read_image(sid)
    res = generate_dataset(load_recipe("simple", TINY), 40, out, seed=0, progress=False, limit=1)
    assert res.skipped >= 2
    assert not [p for p in (out / "meta").glob("*.json") if not ds.image_path(p.stem).exists()]


def _worker_pids(pid: int) -> list[int]:
    """The pool workers (spawned interpreters) among the children of process `pid` (Linux /proc)."""
    kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    return [int(k) for k in kids if b"spawn_main" in Path(f"/proc/{k}/cmdline").read_bytes()]


def test_a_pool_that_breaks_between_two_images_stops_with_the_same_message(tmp_path, monkeypatch):
    """The worker can die just after another image finished: the pool then refuses the next
    image at submit time. That must read like any other crash, not as a traceback."""
    import concurrent.futures as cf
    from concurrent.futures.process import BrokenProcessPool

    import racklay.synth.generate as gen

    class OnceThenBroken:  # runs the first images, then behaves like a pool whose worker was killed
        def __init__(self, *a, **k):
            self.calls = 0

        def submit(self, fn, i):
            self.calls += 1
            if self.calls > 2:
                raise BrokenProcessPool("a child process terminated abruptly")
            f = cf.Future()
            f.set_result((i, {}))
            return f

        def shutdown(self, **k):
            pass

    monkeypatch.setattr(cf, "ProcessPoolExecutor", OnceThenBroken)
    with pytest.raises(gen.WorkerCrash, match="a worker process died while making image .*run the same command"):
        list(gen._pool_results(list(range(10)), 1, (), tmp_path))


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="finds the workers through Linux /proc")
def test_a_worker_killed_mid_run_stops_the_run_with_a_message_and_a_rerun_finishes(tmp_path):
    """A worker that dies (the OOM killer, a crash in the GL driver) must not leave the run
    waiting for ever: the command stops with one line naming the image, and a rerun resumes."""
    import signal
    import time

    out = tmp_path / "crashed"
    cmd = [sys.executable, "-m", "racklay", "synth", "--recipe", "simple", "--n", "200", "--out", str(out),
           "--workers", "2", "--no-progress"] + sum((["--set", s] for s in TINY), [])
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while time.time() - t0 < 60 and not list((out / "meta").glob("*.json")):
        time.sleep(0.05)
    pids = _worker_pids(proc.pid)
    assert pids, "no worker process found"
    os.kill(pids[0], signal.SIGKILL)
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail("the run kept waiting for the killed worker")
    assert proc.returncode != 0
    msg = err.strip().splitlines()
    assert len(msg) == 1 and "a worker process died while making image" in msg[0] and str(out) in msg[0], err
    assert "run the same command again" in msg[0]
    ds = RackLayRoot(out)
    for sid in ds.ids():
        ds.read_image(sid)
    # finished samples: meta is written last (an image without it was cut short: made again)
    before = sum(ds.meta_path(sid).exists() for sid in ds.ids())
    assert 0 < before < 200
    res = generate_dataset(load_recipe("simple", TINY), 200, out, seed=0, progress=False, workers=2)
    assert res.skipped == before and len(res.generated) == 200 - before
    assert check_dataset(out).ok


def test_recipe_errors_before_anything_is_written(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\nbox_densty: [0, 1]\n")
    with pytest.raises(RecipeError, match=r"bad.yaml: unknown key 'box_densty' \(did you mean 'box_density'\?\)"):
        load_recipe(str(bad))
    out = tmp_path / "never"
    assert racklay_main(["synth", "--recipe", str(bad), "--n", "2", "--out", str(out)]) == 2
    assert "box_densty" in capsys.readouterr().err
    assert not out.exists()
    for override, msg in (("yaw_max_deg=90", "out of range"), ("n_shelves=[5,2]", "lo > hi"),
                          ("background={wall: 1, sky: 1}", "unknown choice"), ("shadows=maybe", "true or false"),
                          ("splits={train: 0.9, test: 0.2}", "sum to"), ("nope=1", "unknown key 'nope'")):
        with pytest.raises(RecipeError, match=msg):
            load_recipe("complex", [override])
        assert racklay_main(["synth", "--n", "2", "--out", str(out), "--set", override]) == 2
        assert not out.exists()
    with pytest.raises(RecipeError, match="not found"):
        load_recipe("no_such_recipe")
    # an empty (unsaved, truncated) recipe file is not the defaults in disguise
    (tmp_path / "empty.yaml").write_text("# nothing yet\n")
    with pytest.raises(RecipeError, match=r"empty.yaml: empty recipe"):
        load_recipe(str(tmp_path / "empty.yaml"))


def test_a_recipe_based_on_another_lists_only_what_it_changes(tmp_path):
    """`base: NAME`: a recipe starts from another's keys (a built-in name or a file, recursively),
    its own keys win, its name is its own; a base that is missing, not a name, or the recipe itself
    is one error naming the file. The shipped `mixed_wide` is `mixed` with its coverage keys."""
    import dataclasses

    mixed, wide = load_recipe("mixed"), load_recipe("mixed_wide")
    changed = {f.name for f in dataclasses.fields(mixed) if getattr(mixed, f.name) != getattr(wide, f.name)}
    assert wide.name == "mixed_wide" and wide.pallet_wide_fraction > 0 and wide.shelf_height == mixed.shelf_height
    assert "pallet_wide_fraction" in changed and "shelf_height" not in changed and "jpeg_quality" not in changed
    a = tmp_path / "a.yaml"
    a.write_text("base: mixed_wide\npallet_wide_fraction: 0.5\n")
    r = load_recipe(str(a), ["min_gap=0.05"])
    assert (r.name, r.pallet_wide_fraction, r.flush_fraction, r.min_gap) == ("a", 0.5, wide.flush_fraction, 0.05)
    assert wide.flush_fraction != mixed.flush_fraction
    (tmp_path / "b.yaml").write_text(f"base: {tmp_path / 'c.yaml'}\n")
    (tmp_path / "c.yaml").write_text(f"base: {tmp_path / 'b.yaml'}\n")
    for text, msg in (("base: nosuch\n", r"d.yaml: key 'base': recipe 'nosuch' not found"),
                      ("base: [mixed]\n", r"d.yaml: key 'base': expected a recipe name"),
                      ("base: mixed\nbox_densty: 1\n", r"d.yaml: unknown key 'box_densty'")):
        (tmp_path / "d.yaml").write_text(text)
        with pytest.raises(RecipeError, match=msg):
            load_recipe(str(tmp_path / "d.yaml"))
    with pytest.raises(RecipeError, match="is based on itself"):
        load_recipe(str(tmp_path / "b.yaml"))


def test_existing_folder_with_other_settings_is_refused(tmp_path, reference):
    out = tmp_path / "copy"
    shutil.copytree(reference, out)
    with pytest.raises(ValueError, match="different settings"):
        generate_dataset(tiny(), 6, out, seed=4, progress=False)


def test_atomic_write_without_fsync(tmp_path):
    from racklay.atomic import atomic_write_bytes
    p = atomic_write_bytes(tmp_path / "a" / "f.bin", b"xyz", fsync=False)
    assert p.read_bytes() == b"xyz" and [q.name for q in p.parent.iterdir()] == ["f.bin"]


def test_synth_refuses_a_folder_holding_other_data(tmp_path, capsys):
    """--out pointing at an existing dataset not made by synth (e.g. an annotate export) is
    refused before anything is written: synth would rewrite its splits."""
    from racklay.cli import main

    other = tmp_path / "labelled"
    (other / "splits").mkdir(parents=True)
    (other / "splits" / "train.txt").write_text("Images/000000.png\n")
    assert main(["synth", "--recipe", "simple", "--n", "2", "--out", str(other)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "files not made by racklay synth" in err[0]
    assert sorted(p.name for p in other.rglob("*")) == ["splits", "train.txt"]
    with pytest.raises(SystemExit) as e:   # argparse: one usage line, exit 2
        main(["synth", "--recipe", "simple", "--n", "0", "--out", str(tmp_path / "x")])
    assert e.value.code == 2 and not (tmp_path / "x").exists()


def test_relayout_redraws_the_layouts_as_a_new_render_would(tmp_path, capsys):
    """`racklay synth --relayout SET --set layout_extent=row` gives, without rendering, the files a
    render of the same recipe, seed and layout key gives (layouts, meta, splits, COCO), the images
    and maps hard-linked from SET; other keys, --n beside it, no key change and a changed scene are refused."""
    mixed = ["image_width=200", "image_height=120", "layout_size=64"]
    src, direct, out = tmp_path / "bay", tmp_path / "row", tmp_path / "relaid"
    generate_dataset(load_recipe("mixed", mixed), 6, src, seed=3, progress=False)
    generate_dataset(load_recipe("mixed", mixed + ["layout_extent=row"]), 6, direct, seed=3, progress=False)
    assert racklay_main(["synth", "--relayout", str(src), "--out", str(out), "--set", "layout_extent=row",
                         "--no-progress"]) == 0
    got, want, before = files(out), files(direct), files(src)
    del got["waresynth.json"], want["waresynth.json"]
    assert got == want
    assert any(got[k] != before[k] for k in got if k.endswith(".npy"))   # the row convention drew something else
    img = "Images/000000.png"
    assert (out / img).stat().st_ino == (src / img).stat().st_ino
    man = json.loads((out / "waresynth.json").read_text())
    assert man["recipe"]["layout_extent"] == "row" and man["relayout_of"]["path"] == str(src.resolve())
    assert check_dataset(out).ok
    # only layout keys; nothing written for a refused call
    for args, msg in ((["--set", "box_density=[0,1]"], "can change only layout_extent"),
                      (["--set", "layout_extent=row", "--n", "6"], "drop --n"),
                      (["--set", "layout_extent=bay"], "give a layout key to change")):
        assert racklay_main(["synth", "--relayout", str(src), "--out", str(tmp_path / "no"), *args]) == 2
        assert msg in capsys.readouterr().err and not (tmp_path / "no").exists()
    # a scene that is not the one rendered (other generator code) is refused, naming its meta
    meta = src / "meta" / "000004.json"
    m = json.loads(meta.read_text())
    m["camera"]["t"][0] += 0.01
    meta.write_text(json.dumps(m))
    assert racklay_main(["synth", "--relayout", str(src), "--out", str(tmp_path / "bad"),
                         "--set", "layout_size=128", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "000004.json" in err and "camera t" in err and "render it anew" in err
