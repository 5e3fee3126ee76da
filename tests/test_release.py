"""The shipped model: it is in the package, intact (sha256), used when no weights are given, and
the quick demo runs end to end from it."""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import REAL_PHOTOS, REPO, run_module
from racklay import release
from racklay.checkpoint import load_model

PHOTO = REAL_PHOTOS / "19_mock_white_shelf_3lvl.jpg"
LEVELS = REAL_PHOTOS / "15_loco_red_racks_jacks.jpg"      # a pallet rack with four beam levels in view


def test_shipped_weights_are_intact_small_and_load():
    path = release.release_weights()
    assert path.stat().st_size <= 25 * 2**20
    assert release.sha256_file(path) == release.RELEASE_SHA256
    model, cfg, meta = load_model(path)
    assert cfg.encoder == "efficientnet-lite0" and set(cfg.views) == {"top", "front"}
    assert cfg.decoder == "struct"       # boxes as rectangles, scale explicit (docs/model-card.md)
    assert meta.get("storage") == "fp16" and "train_config" in meta


def test_corrupt_shipped_weights_are_refused(tmp_path, monkeypatch):
    bad = tmp_path / release.RELEASE_NAME
    shutil.copyfile(release.release_weights(), bad)
    with open(bad, "r+b") as f:
        f.seek(-100, 2)
        f.write(b"\x00" * 8)
    monkeypatch.setattr(release, "WEIGHTS_DIR", tmp_path)
    monkeypatch.setattr(release, "_verified", set())
    with pytest.raises(ValueError, match="sha256.*does not match"):
        release.release_weights()


def test_average_checkpoints_writes_the_mean_model_with_its_sources(tmp_path):
    """A model soup: float tensors (BN statistics too) are the mean, integer counters and the
    training facts come from the last checkpoint, sources are recorded; another architecture is
    refused; the release file made from it keeps the record."""
    import torch

    from racklay.checkpoint import load_checkpoint, save_checkpoint
    from racklay.model import ModelConfig, RackLayNet

    cfg = ModelConfig(R=2, image_size=64, layout_size=32, encoder="resnet18")
    paths = []
    for i in range(2):
        torch.manual_seed(i)
        net = RackLayNet(cfg)
        net.decoders["top"].head.bias.data.fill_(float(i))
        net.encoder.bn1.running_mean.fill_(2.0 * i)
        net.encoder.bn1.num_batches_tracked.fill_(10 * (i + 1))
        paths.append(save_checkpoint(tmp_path / f"m{i}.safetensors", net, cfg,
                                     extra={"train_config": {"iou_weight": float(i)}}))
    a, b = (load_checkpoint(p).section("model") for p in paths)
    out = release.average_checkpoints(paths, tmp_path / "soup.safetensors")
    ck = load_checkpoint(out)
    sd = ck.section("model")
    k = "decoders.top.convs.0.0.weight"
    assert torch.allclose(sd[k], (a[k] + b[k]) / 2)
    assert torch.allclose(sd["decoders.top.head.bias"], torch.full_like(sd["decoders.top.head.bias"], 0.5))
    assert torch.allclose(sd["encoder.bn1.running_mean"], torch.ones_like(sd["encoder.bn1.running_mean"]))
    assert int(sd["encoder.bn1.num_batches_tracked"]) == 20
    assert ck.meta["train_config"] == {"iou_weight": 1.0} and ck.meta["averaged_from"] == [str(p) for p in paths]
    assert load_checkpoint(release.make_release(out, tmp_path / "rel.safetensors")).meta["averaged_from"] == \
        ck.meta["averaged_from"]
    w = load_checkpoint(release.average_checkpoints(paths, tmp_path / "w.safetensors", weights=[7, 3]))
    assert torch.allclose(w.section("model")[k], (0.7 * a[k].double() + 0.3 * b[k].double()).float())
    assert w.meta["averaged_weights"] == pytest.approx([0.7, 0.3])
    with pytest.raises(ValueError, match="non-negative weights"):
        release.average_checkpoints(paths, tmp_path / "bad.safetensors", weights=[1, -1])
    other = ModelConfig(R=3, image_size=64, layout_size=32, encoder="resnet18")
    odd = save_checkpoint(tmp_path / "odd.safetensors", RackLayNet(other), other)
    with pytest.raises(ValueError, match="odd.safetensors.*config differs"):
        release.average_checkpoints([odd, paths[0]], tmp_path / "bad.safetensors")


def test_graft_update_adds_a_fine_tunes_change_to_another_model(tmp_path):
    """base + alpha x (finetuned - start), config and training facts from base, the recipe recorded
    (and kept by make_release); with base = start it is the weighted soup; BN variances stay >= 0;
    alpha outside [0, 1] and another architecture are refused."""
    import torch

    from racklay.checkpoint import load_checkpoint, save_checkpoint
    from racklay.model import ModelConfig, RackLayNet

    cfg = ModelConfig(R=2, image_size=64, layout_size=32, encoder="resnet18")
    paths = {}
    for i, name in enumerate(("start", "base", "ft")):
        torch.manual_seed(i)
        net = RackLayNet(cfg)
        net.encoder.bn1.running_var.fill_((0.1, 0.1, 1.0)[i])
        paths[name] = save_checkpoint(tmp_path / f"{name}.safetensors", net, cfg,
                                      extra={"train_config": {"iou_weight": float(i)}})
    sds = {n: load_checkpoint(p).section("model") for n, p in paths.items()}
    out = release.graft_update(paths["base"], paths["start"], paths["ft"], tmp_path / "g.safetensors", alpha=0.3)
    ck = load_checkpoint(out)
    k = "decoders.front.convs.1.0.weight"
    want = sds["base"][k].double() + 0.3 * (sds["ft"][k].double() - sds["start"][k].double())
    assert torch.allclose(ck.section("model")[k].double(), want, atol=1e-6)
    assert ck.meta["train_config"] == {"iou_weight": 1.0}
    assert ck.meta["grafted"] == {"base": str(paths["base"]), "start": str(paths["start"]),
                                  "finetuned": str(paths["ft"]), "alpha": 0.3}
    assert load_checkpoint(release.make_release(out, tmp_path / "rel.safetensors")).meta["grafted"]["alpha"] == 0.3
    same = load_checkpoint(release.graft_update(paths["start"], paths["start"], paths["ft"], tmp_path / "s.safetensors", 0.3))
    soup = load_checkpoint(release.average_checkpoints([paths["start"], paths["ft"]], tmp_path / "soup.safetensors",
                                                       weights=[0.7, 0.3]))
    assert torch.allclose(same.section("model")[k], soup.section("model")[k], atol=1e-6)
    # 0.1 + 2 x (0.1 - 1.0) < 0 is not a variance: clamped
    neg = load_checkpoint(release._weighted_sum([paths["base"], paths["ft"], paths["start"]], [1.0, -2.0, 2.0],
                                                tmp_path / "n.safetensors", 0, {}))
    assert float(neg.section("model")["encoder.bn1.running_var"].min()) == 0.0
    with pytest.raises(ValueError, match="alpha must be in"):
        release.graft_update(paths["base"], paths["start"], paths["ft"], tmp_path / "bad.safetensors", alpha=1.5)
    other = ModelConfig(R=3, image_size=64, layout_size=32, encoder="resnet18")
    odd = save_checkpoint(tmp_path / "odd.safetensors", RackLayNet(other), other)
    with pytest.raises(ValueError, match="odd.safetensors.*config differs"):
        release.graft_update(paths["base"], odd, paths["ft"], tmp_path / "bad.safetensors", alpha=0.3)

@pytest.mark.slow
def test_predict_without_weights_uses_the_shipped_model_finds_the_shelves_and_takes_a_known_length(tmp_path):
    """The shipped model on a real photo finds its shelves in both views; `--shelf-length 1.2`
    makes every shelf 1.2 m long and changes nothing else (which shelves, where boxes stand along
    each shelf)."""
    from racklay import layout as L
    from racklay.data import RackLayRoot

    lays = {}
    for name, extra in (("own", []), ("known", ["--shelf-length", "1.2"])):
        out = tmp_path / name
        r = run_module("racklay", "predict", LEVELS, "--out", out, "--no-png", *extra, cwd=REPO)
        assert r.returncode == 0, r.stderr
        assert "shipped model" in r.stderr
        root = RackLayRoot(out)
        lays[name] = {v: root.read_layouts(v, LEVELS.stem) for v in ("top", "front")}
    assert (tmp_path / "own" / "figures" / f"{LEVELS.stem}.png").is_file()
    own, known = lays["own"], lays["known"]
    grid = L.Grid(256, 8.0)
    for v in ("top", "front"):
        assert own[v].shape == (4, 256, 256)
        # a rack with several levels in view: the shipped model finds at least two in both views
        present = [int((ch != L.BACKGROUND).sum()) >= 500 for ch in own[v]]
        assert sum(present) >= 2
        assert [int((ch != L.BACKGROUND).sum()) > 0 for ch in known[v]] == [int((ch != L.BACKGROUND).sum()) > 0 for ch in own[v]]
        for a, b, here in zip(own[v], known[v], present):
            if not here:
                continue
            assert L.shelf_lengths(b[None], grid)[0] == pytest.approx(1.2, abs=2 * grid.res)
            # where boxes stand, as a fraction of the shelf's length: unchanged by the scale
            share = [float((x == L.BOX).any(0).sum()) / max(float((x != L.BACKGROUND).any(0).sum()), 1.0) for x in (a, b)]
            assert share[1] == pytest.approx(share[0], abs=0.05)


@pytest.mark.slow
def test_shipped_model_draws_separate_boxes_where_a_photo_shows_them_apart():
    """Pallet loads standing apart (photo 126, a frame of video IMG_0267 of the pallet-racking test
    site, a video no model was trained on): the shipped struct model draws them as separate
    rectangles on their board, not one band per shelf (v5 drew bands): in the front view (rows
    top-down in z) every shelf's lowest box row is its board's row. (v11 draws separate boxes this
    way on 5 of the 43 test photos, v10 on 4, both on this one: docs/model-card.md, "Known limits".)"""
    from racklay import layout as L
    from racklay.data import read_image
    from racklay.predict import Predictor

    pred = Predictor(str(release.release_weights()))
    out = pred.predict(read_image(REAL_PHOTOS / "126_palletvid0267_f216.jpg"))
    front = out["front"]
    assert L.box_runs(front).max() >= 2
    for ch in front:
        if (ch == L.BOX).any():
            rows = np.nonzero((ch != L.BACKGROUND).any(1))[0]
            box_rows = np.nonzero((ch == L.BOX).any(1))[0]
            assert box_rows.max() == rows.max()


@pytest.mark.slow
def test_quick_demo_runs_end_to_end_from_the_shipped_model(tmp_path, capsys):
    """`transfer demo --quick` (the README's main job, `make demo`, reduced) through its command line."""
    from transfer.cli import main as transfer_main

    out = tmp_path / "demo"
    assert transfer_main(["demo", "--quick", "--out", str(out)]) == 0
    log = capsys.readouterr().out
    from transfer.demo import PHOTOS

    photos = sorted(p.stem for p in PHOTOS.iterdir() if p.suffix == ".jpg")
    figs = out / "real-photo-predictions"
    assert sorted(p.stem for p in figs.glob("*.png") if p.stem != "contact_sheet") == photos
    assert (figs / "contact_sheet.png").is_file() and (figs / "SOURCES.tsv").is_file()
    assert f"the shipped model ({release.RELEASE_NAME})" in log
    gain = re.search(r"fine-tuned vs real only, top-view box mIoU: ([\d.]+) vs ([\d.]+)", log)
    assert gain and all(np.isfinite(float(g)) for g in gain.groups())
    assert (out / "compare" / "runs" / "seed0" / "finetune_f1" / "best.safetensors").is_file()
    table = (out / "compare" / "table.md").read_text().lower()
    for row in ("synthetic only", "real only", "fine-tune"):
        assert row in table


def labelled_project(tmp_path, split: dict) -> Path:
    """A small annotate project of photos of datasets/real-photos with their labels and a
    SOURCES.tsv giving each its split ({photo name: split})."""
    proj = tmp_path / "photos"
    (proj / "annotations").mkdir(parents=True)
    for name in split:
        shutil.copy(REAL_PHOTOS / name, proj / name)
        shutil.copy(REAL_PHOTOS / "annotations" / f"{name}.json", proj / "annotations" / f"{name}.json")
    shutil.copy(REAL_PHOTOS / "project.json", proj / "project.json")
    (proj / "SOURCES.tsv").write_text("file\tsplit\n" + "".join(f"{n}\t{s}\n" for n, s in split.items()))
    return proj


@pytest.mark.slow
def test_quick_demo_table2_on_labelled_real_photos(tmp_path, capsys):
    """`transfer demo --real-photos PROJECT` (what `make demo` runs): Table 2 on labelled photos,
    each in the split its SOURCES.tsv row names (here 6 photos of datasets/real-photos: three
    training sites, one test site); a SOURCES.tsv without a test photo is a one-line error."""
    from racklay.data import check_dataset
    from transfer.cli import main as transfer_main

    split = {"04_blueshelf_surf.jpg": "train", "05_blueshelf_tulip.jpg": "train", "16_loco_red_rack_bins.jpg": "train",
             "19_mock_white_shelf_3lvl.jpg": "train", "30_palletvid0263_f051.jpg": "test",
             "49_palletvid0265_f043.jpg": "test"}
    proj = labelled_project(tmp_path, split)
    out = tmp_path / "demo"
    assert transfer_main(["demo", "--quick", "--out", str(out), "--photos", str(proj),
                          "--real-photos", str(proj)]) == 0
    log = capsys.readouterr().out
    assert "splits train=4, test=2" in log and "Table 2 on the labelled real photos' test split" in log
    assert check_dataset(out / "data" / "real-photos").splits == {"train": 4, "test": 2}
    assert "real only" in (out / "compare" / "table.md").read_text().lower()
    (proj / "SOURCES.tsv").write_text("file\tsplit\n" + "".join(f"{n}\ttrain\n" for n in split))
    assert transfer_main(["demo", "--quick", "--out", str(tmp_path / "demo2"), "--photos", str(proj),
                          "--real-photos", str(proj)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "SOURCES.tsv" in err[0] and "both train and test" in err[0], err


def test_demo_reuses_the_real_export_until_labels_or_splits_change(tmp_path):
    """The demo's export of the labelled photos is reused on a second run, and made again (not
    silently reused) once a label or a split has changed."""
    from annotate.store import Project
    from transfer.demo import _export_real

    proj = labelled_project(tmp_path, {"04_blueshelf_surf.jpg": "train", "30_palletvid0263_f051.jpg": "test"})
    out, logs = tmp_path / "data" / "real-photos", []
    _export_real(proj, out, logs.append)
    _export_real(proj, out, logs.append)
    assert "labelled photos exported" in logs[0] and "reused" in logs[1]
    project = Project(proj)
    ann = project.load("04_blueshelf_surf.jpg")
    ann["rack"]["width"] = 1.5
    project.save(ann)
    _export_real(proj, out, logs.append)
    assert "changed since the last run" in logs[2] and "labelled photos exported" in logs[3]


def test_toy_demo_builds_checks_scores_and_draws(tmp_path, capsys):
    """`transfer demo --toy`: the seconds-long schematic demo of the data and metrics layer."""
    from transfer.cli import main as transfer_main

    out = tmp_path / "toy"
    assert transfer_main(["demo", "--toy", "--n", "6", "--out", str(out)]) == 0
    log = capsys.readouterr().out
    assert "6 samples" in log and "-> OK" in log
    scores = json.loads((out / "scores.json").read_text())
    # boxes eroded and a shelf dropped: worse than perfect, better than nothing
    assert 0 < scores["top"]["dataset"]["box"]["IoU"] < 1
    assert (out / "figure.png").is_file() and len(list((out / "degraded-predictions" / "topLayouts").iterdir())) == 6
