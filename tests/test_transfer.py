"""Sim-to-real transfer: the paper's augmentation, pretrain -> finetune, compare (Table 2), and
their error messages. Tiny sizes throughout (image 64, layout 32) on toy datasets."""
from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import pytest

from racklay import layout as L
from racklay.toy import build_toy_dataset
from transfer.augment import AugmentConfig, PaperAugment


# --------------------------------------------------------------------------- augmentation
def _asymmetric_sample(R=4, S=32, H=40, W=72):
    """An image whose left third is bright red with a white stripe, and layouts in which every
    channel of both views has its own off-centre content (so any column swap or channel mix-up
    shows)."""
    img = np.zeros((H, W, 3), np.uint8)
    img[:, : W // 3] = (200, 30, 30)
    img[5:9, 2:10] = 255
    img[:, W // 3: W // 2] = (20, 150, 40)
    lays = {}
    for k, v in enumerate(("top", "front")):
        a = np.zeros((R, S, S), np.uint8)
        for r in range(R):
            c0 = 1 + 3 * r + k
            a[r, 2 + r: 12 + r, c0: c0 + 6] = L.SHELF
            a[r, 4 + r: 8 + r, c0 + 1: c0 + 3 + r] = L.BOX
        lays[v] = a
    return img, lays


def test_flip_moves_image_and_every_layout_channel_together():
    img, lays = _asymmetric_sample()
    aug = PaperAugment(seed=0, config=AugmentConfig(jitter_p=0.0, flip_p=1.0))
    out, got = aug(img, {v: a.copy() for v, a in lays.items()})
    np.testing.assert_array_equal(out, img[:, ::-1])
    W, S = img.shape[1], 32
    for v in ("top", "front"):
        assert got[v].shape == lays[v].shape and got[v].dtype == np.uint8
        np.testing.assert_array_equal(got[v], L.hflip_layouts(lays[v]))
        for r in range(lays[v].shape[0]):
            # pixel correspondence: column c of the original is column S-1-c after the flip
            rows, cols = np.nonzero(lays[v][r] == L.BOX)
            assert (got[v][r][rows, S - 1 - cols] == L.BOX).all()
            assert not (got[v][r][rows, cols] == L.BOX).all()  # it really moved (off-centre content)
    # the image's red third is now on the right, and so is the marker stripe
    assert (out[:, -1] == (200, 30, 30)).all() and (out[5:9, W - 10: W - 2] == 255).all()


def test_random_draws_flip_image_and_layouts_consistently_and_keep_values():
    img, lays = _asymmetric_sample()
    aug = PaperAugment(seed=123)  # the paper's parameters: jitter p=0.5, flip p=0.5
    flips = jitters = 0
    for _ in range(40):
        out, got = aug(img, {v: a.copy() for v, a in lays.items()})
        applied = [name for name, _ in aug.last_applied]
        jittered = "ColorJitter" in applied
        # which way is the image? compare against both orientations (robust to colour jitter)
        d_same = np.abs(out.astype(int) - img).mean()
        d_flip = np.abs(out.astype(int) - img[:, ::-1]).mean()
        image_flipped = d_flip < d_same
        for v in ("top", "front"):
            expect = L.hflip_layouts(lays[v]) if image_flipped else lays[v]
            np.testing.assert_array_equal(got[v], expect)
            assert set(np.unique(got[v])) == set(np.unique(lays[v]))
        assert image_flipped == ("HorizontalFlip" in applied)
        flips += image_flipped
        jitters += jittered
    assert 8 <= flips <= 32 and 8 <= jitters <= 32  # both p = 0.5


def test_colour_jitter_never_touches_layouts():
    img, lays = _asymmetric_sample()
    aug = PaperAugment(seed=1, config=AugmentConfig(jitter_p=1.0, flip_p=0.0))
    changed = 0
    for _ in range(10):
        out, got = aug(img, {v: a.copy() for v, a in lays.items()})
        changed += not np.array_equal(out, img)
        for v in ("top", "front"):
            np.testing.assert_array_equal(got[v], lays[v])
    assert changed >= 9
    # jitter parameters within the paper's ranges
    params = dict(aug.last_applied)["ColorJitter"]
    assert 0.8 <= params["brightness"] <= 1.2 and -0.1 <= params["hue"] <= 0.1


def test_augmentation_is_reproducible_by_seed():
    img, lays = _asymmetric_sample()

    def run(seed):
        aug = PaperAugment(seed=seed)
        return [aug(img, lays)[0] for _ in range(8)]

    a, b, c = run(7), run(7), run(8)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))


def test_augmentation_reseeds_per_dataloader_worker(monkeypatch):
    import torch.utils.data as tud

    img, lays = _asymmetric_sample()

    def draws(worker_seed):
        monkeypatch.setattr(tud, "get_worker_info", lambda: types.SimpleNamespace(seed=worker_seed, id=0))
        aug = PaperAugment(seed=5)
        return [tuple(n for n, _ in (aug(img, lays), aug.last_applied)[1]) for _ in range(16)]

    assert draws(1000) == draws(1000)
    assert draws(1000) != draws(1001)


def test_augmentation_plugs_into_racklay_dataset(tmp_path):
    from racklay.torchdata import RackLayDataset

    build_toy_dataset(tmp_path / "toy", n=6, seed=0, D=64)
    plain = RackLayDataset(tmp_path / "toy", split=None, image_size=64, layout_size=32)
    aug = RackLayDataset(tmp_path / "toy", split=None, image_size=64, layout_size=32,
                         transform=PaperAugment(seed=0, config=AugmentConfig(jitter_p=0.0, flip_p=1.0)))
    for i in range(len(plain)):
        a, b = plain[i], aug[i]
        assert b["image"].shape == (3, 64, 64) and b["top"].shape == (4, 32, 32)
        np.testing.assert_allclose(b["image"].numpy(), a["image"].numpy()[:, :, ::-1])
        for v in ("top", "front"):
            np.testing.assert_array_equal(b[v].numpy(), a[v].numpy()[..., ::-1])


def test_augmentation_rejects_bad_input():
    img, lays = _asymmetric_sample()
    aug = PaperAugment(seed=0)
    with pytest.raises(ValueError, match="RGB uint8"):
        aug(img.astype(np.float32), lays)
    with pytest.raises(ValueError, match=r"\(R, S, S\)"):
        aug(img, {"top": lays["top"][0]})


# --------------------------------------------------------------------------- training workflow
TINY = dict(image_size=64, layout_size=32, batch_size=4, disc=False, workers=0, progress=False)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    base = tmp_path_factory.mktemp("transfer")
    build_toy_dataset(base / "syn", n=14, seed=0, D=64)                                  # train/val/test
    build_toy_dataset(base / "real", n=14, seed=1, D=64, splits={"train": 0.65, "test": 0.35})  # no val
    return base


# a compare run (about a minute): every test that uses it is marked slow
@pytest.fixture(scope="module")
def killed_then_resumed_compare(tiny_data, monkeypatch_module):
    """A compare killed in its second training run, then started again with the same settings."""
    import racklay.train as rt
    from transfer.compare import CompareConfig, compare

    cfg = CompareConfig(real=str(tiny_data / "real"), out=str(tiny_data / "cmp"), synthetic=str(tiny_data / "syn"),
                        seeds=[0], fractions=[1.0], epochs=1, pretrain_epochs=1, lr=3e-3, val_fraction=0.25,
                        train={"image_size": 64, "layout_size": 32, "batch_size": 4, "disc": False, "workers": 0,
                               "warmup_steps": 0, "progress": False})
    real_train = rt.train
    calls = []

    def dying_train(c, transform=None):
        calls.append(c.name)
        if len(calls) == 2:
            raise KeyboardInterrupt("killed")   # as if the process died during the real-only run
        return real_train(c, transform=transform)

    monkeypatch_module.setattr(rt, "train", dying_train)
    with pytest.raises(KeyboardInterrupt):
        compare(cfg, log=lambda *a: None)
    first = list(calls)
    done_before = {p.parent.name: p.stat().st_mtime_ns for p in (tiny_data / "cmp").rglob("result.json")}
    res = compare(cfg, log=lambda *a: None)
    return {"cfg": cfg, "first": first, "calls": calls, "done_before": done_before, "res": res}


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


@pytest.mark.slow
def test_compare_writes_table2_rows_and_files(killed_then_resumed_compare):
    out = Path(killed_then_resumed_compare["cfg"].out)
    md = (out / "table.md").read_text()
    for row in ("| synthetic only (n=1) |", "| real only (n=1) |", "| synthetic → real fine-tune (n=1) |"):
        assert row in md
    assert "top box mIoU" in md and "top box IoU" in md and "Targets" in md
    lines = (out / "table.csv").read_text().splitlines()
    assert [l.split(",")[0] for l in lines[1:]] == ["synthetic", "real", "finetune"]
    assert "top box mIoU mean" in lines[0] and "top box IoU std" in lines[0]
    assert "front shelves in place mean" in lines[0] and "Boxes as boxes (front view;" in md
    runs = (out / "runs.csv").read_text().splitlines()
    assert len(runs) == 1 + 3
    for png in ("chart.png", "learning_curve.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    recs = killed_then_resumed_compare["res"]["records"]
    assert {r["regime"] for r in recs} == {"synthetic", "real", "finetune"}
    ft = next(r for r in recs if r["regime"] == "finetune")
    assert ft["n_train"] == 7 and ft["metrics"]["top"]["images"] == 5   # 9 train - 25% val; 5 test
    # every number in the table comes from a real evaluation
    assert all(0 <= r["metrics"]["top"]["paper"]["box"]["mIoU"] <= 1 for r in recs)


@pytest.mark.slow
def test_killed_compare_resumes_without_redoing_finished_runs(killed_then_resumed_compare):
    k = killed_then_resumed_compare
    assert k["first"] == ["pretrain", "real_f1"]             # died in the 2nd training run
    assert set(k["done_before"]) == {"pretrain", "synthetic"}  # finished before the kill
    assert k["calls"][2:] == ["real_f1", "finetune_f1"]       # resume: no second pretrain
    out = Path(k["cfg"].out)
    for name, mtime in k["done_before"].items():
        p = next(out.rglob(f"{name}/result.json"))
        assert p.stat().st_mtime_ns == mtime                  # untouched
    assert k["res"]["summary"]["ran"] == ["seed0/real_f1", "seed0/finetune_f1"]
    assert not list(out.rglob("*.tmp*"))                      # no half-written files


@pytest.mark.slow
def test_compare_refuses_to_resume_with_different_settings(killed_then_resumed_compare):
    import dataclasses

    from transfer.compare import compare

    cfg = dataclasses.replace(killed_then_resumed_compare["cfg"], epochs=5)
    with pytest.raises(ValueError, match="started with epochs=1, now epochs=5"):
        compare(cfg, log=lambda *a: None)


def _real_loss(weights, root) -> float:
    """The training loss (weighted per-shelf cross-entropy) of a checkpoint on a real training split."""
    import torch

    from racklay.checkpoint import load_model
    from racklay.losses import layout_loss
    from racklay.torchdata import RackLayDataset

    model, cfg, _ = load_model(weights)
    ds = RackLayDataset(root, split="train", image_size=cfg.image_size, layout_size=cfg.layout_size)
    batch = torch.utils.data.default_collate([ds[i] for i in range(len(ds))])
    w = torch.tensor([1.0, 5.0, 5.0])
    with torch.no_grad():
        out = model(batch["image"])
    return float(sum(layout_loss(out[v], batch[v], w) for v in cfg.views))


@pytest.mark.slow
def test_finetune_loads_pretrain_checkpoint_and_improves(killed_then_resumed_compare, tiny_data, tmp_path, capsys):
    from transfer.cli import main

    init = Path(killed_then_resumed_compare["cfg"].out) / "runs/seed0/pretrain/best.safetensors"
    real = tiny_data / "real"
    rc = main(["finetune", "--init", str(init), "--real", str(real), "--out", str(tmp_path / "ft"),
               "--epochs", "2", "--lr", "3e-3", "--batch-size", "4", "--val-fraction", "0.25", "--patience", "10"])
    assert rc == 0
    out = capsys.readouterr().out
    assert str(tmp_path / "ft" / "best.safetensors") in out
    import yaml
    cfg = yaml.safe_load((tmp_path / "ft" / "config.yaml").read_text())
    assert cfg["init"] == str(init) and cfg["image_size"] == 64 and cfg["layout_size"] == 32  # from the checkpoint
    before, after = _real_loss(init, real), _real_loss(tmp_path / "ft" / "last.safetensors", real)
    assert after < 0.8 * before, (before, after)


@pytest.mark.slow
def test_finetune_rejects_checkpoint_with_other_R_or_D(killed_then_resumed_compare, tiny_data, tmp_path):
    from transfer.cli import main
    from transfer.workflow import check_init_compatible

    init = Path(killed_then_resumed_compare["cfg"].out) / "runs/seed0/pretrain/best.safetensors"
    build_toy_dataset(tmp_path / "r3", n=4, seed=2, R=3, D=64, splits={"train": 0.5, "test": 0.5})
    with pytest.raises(ValueError, match=r"R=4 shelves, but .*r3 has R=3"):
        check_init_compatible(init, tmp_path / "r3")
    with pytest.raises(ValueError, match=r"predicts 32x32 layouts \(D\) with the \w+ decoder, but layout size 64"):
        check_init_compatible(init, tiny_data / "real", layout_size=64)
    # and through the command line: one line, exit code 2, nothing trained
    assert main(["finetune", "--init", str(init), "--real", str(tmp_path / "r3"), "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()


def test_finetune_takes_a_struct_checkpoint_at_another_layout_size(tmp_path):
    """`transfer finetune --layout-size 64` from a struct checkpoint trained at 32² is accepted
    (its structure is drawn at any size, as `racklay train --init` allows); from a dense one it is
    refused with one line naming the file and both sizes."""
    import torch

    from racklay.checkpoint import save_checkpoint
    from racklay.config import ModelConfig
    from racklay.model import RackLayNet
    from transfer.workflow import check_init_compatible

    build_toy_dataset(tmp_path / "real", n=4, seed=2, R=2, D=64, splits={"train": 0.5, "test": 0.5})
    torch.manual_seed(0)
    paths = {}
    for dec in ("struct", "light"):
        extra = {"struct_width": 16} if dec == "struct" else {}
        net = RackLayNet(ModelConfig(R=2, image_size=(64, 128), layout_size=32, decoder=dec, **extra))
        paths[dec] = save_checkpoint(tmp_path / f"{dec}32.safetensors", net, net.cfg)
    assert check_init_compatible(paths["struct"], tmp_path / "real", layout_size=64).decoder == "struct"
    with pytest.raises(ValueError, match=r"light32.safetensors: checkpoint predicts 32x32 layouts \(D\) with the "
                                         r"light decoder, but layout size 64"):
        check_init_compatible(paths["light"], tmp_path / "real", layout_size=64)


def test_missing_split_names_the_splits_found(tiny_data, tmp_path, capsys):
    from transfer.cli import main

    rc = main(["compare", "--synthetic", str(tiny_data / "syn"), "--real", str(tiny_data / "real"),
               "--test-split", "val", "--out", str(tmp_path / "c")])
    err = capsys.readouterr().err
    assert rc == 2 and "val.txt: split file not found" in err and "test, train" in err
    rc = main(["finetune", "--real", str(tmp_path), "--out", str(tmp_path / "f")])   # from the shipped model
    assert rc == 2 and "split file not found (splits found in" in capsys.readouterr().err
    real = str(tiny_data / "real")
    rc = main(["finetune", "--init", "nowhere.safetensors", "--real", real, "--out", str(tmp_path / "f")])
    assert rc == 2 and "nowhere.safetensors: weights file not found" in capsys.readouterr().err
    # a run folder given for the checkpoint names the flag and the weights inside it; a missing
    # replay set is found before any model is loaded
    run = tmp_path / "run"
    run.mkdir()
    (run / "best.safetensors").write_bytes(b"")
    rc = main(["finetune", "--init", str(run), "--real", real, "--out", str(tmp_path / "f")])
    assert rc == 2 and "--init is a folder, not a weights file (it holds best.safetensors" in capsys.readouterr().err
    rc = main(["finetune", "--init", str(run / "best.safetensors"), "--real", real, "--replay", str(tmp_path / "nope"),
               "--out", str(tmp_path / "f")])
    assert rc == 2 and "nope: replay dataset folder not found" in capsys.readouterr().err
    assert not (tmp_path / "f").exists()


def test_corrupt_checkpoint_is_a_clear_error(tiny_data, tmp_path, capsys):
    from transfer.cli import main

    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a checkpoint")
    assert main(["finetune", "--init", str(bad), "--real", str(tiny_data / "real"), "--out", str(tmp_path / "f")]) == 2
    assert f"{bad}: not a readable safetensors checkpoint" in capsys.readouterr().err


def test_compare_plan_is_seed_major_and_scores_a_shared_checkpoint_once(tmp_path):
    from transfer.compare import Compare, CompareConfig

    per_seed = Compare(CompareConfig(real="r", out=str(tmp_path), synthetic="s", seeds=[0, 1], fractions=[0.5, 1.0]))
    assert per_seed.jobs() == [(0, "synthetic", None), (0, "real", 1.0), (0, "finetune", 1.0), (0, "real", 0.5),
                               (0, "finetune", 0.5), (1, "synthetic", None), (1, "real", 1.0), (1, "finetune", 1.0),
                               (1, "real", 0.5), (1, "finetune", 0.5)]
    shared = Compare(CompareConfig(real="r", out=str(tmp_path), pretrained="p.safetensors", seeds=[0, 1], fractions=[1.0]))
    assert [j for j in shared.jobs() if j[1] == "synthetic"] == [(0, "synthetic", None)]
    assert shared.job_dir(1, "finetune", 1.0) == tmp_path / "runs" / "seed1" / "finetune_f1"


def test_strong_augmentation_keeps_layouts_and_letterboxes_only_the_image():
    from racklay.augment import make_augment
    from racklay.torchdata import PAD_RGB

    img, lays = _asymmetric_sample()
    img = np.ascontiguousarray(np.broadcast_to(np.linspace(30, 220, img.shape[1])[None, :, None], img.shape).astype(np.uint8))
    aug = make_augment("strong", seed=5, letterbox=True)
    boxed = changed = 0
    for _ in range(60):
        out, got = aug(img, {v: a.copy() for v, a in lays.items()})
        assert out.shape == img.shape and out.dtype == np.uint8
        flipped = np.array_equal(got["top"], L.hflip_layouts(lays["top"]))
        for v in ("top", "front"):   # layouts: untouched or flipped with the image, never recoloured
            want = L.hflip_layouts(lays[v]) if flipped else lays[v]
            np.testing.assert_array_equal(got[v], want)
        changed += not np.array_equal(out, img[:, ::-1] if flipped else img)
        boxed += bool((out[:, 0] == PAD_RGB).all() and (out[:, -1] == PAD_RGB).all())
    assert changed >= 40 and 5 <= boxed <= 35      # letterbox p = 0.3
    assert make_augment("none") is None
    with pytest.raises(ValueError, match="augment must be one of"):
        make_augment("heavy")


def test_letterbox_pads_other_aspects_and_resizes_the_same_aspect():
    from racklay.torchdata import PAD_RGB, prepare_image

    square = np.full((100, 100, 3), 200, np.uint8)
    out = prepare_image(square, (64, 112), letterbox=True)
    assert out.shape == (64, 112, 3)
    assert (out[:, :24] == PAD_RGB).all() and (out[:, -24:] == PAD_RGB).all() and (out[:, 24:88] == 200).all()
    wide = np.full((280, 470, 3), 90, np.uint8)     # WareSynth's 470x280 is within 10 % of 112/64: stretched
    assert (prepare_image(wide, (64, 112), letterbox=True) == 90).all()
    assert (prepare_image(square, (64, 112)) == 200).all()   # without letterbox: stretched


@pytest.mark.parametrize("given, expected", [(None, (1.0, 3.0, 7.0)), ((1.0, 2.0, 2.0), (1.0, 2.0, 2.0))])
def test_finetune_keeps_the_loss_the_checkpoint_was_trained_with(tiny_data, tmp_path, monkeypatch, given, expected):
    """A fine-tune uses the init model's loss (class weights, soft-IoU and gap weights, from its
    metadata) unless told otherwise: the release model learned boxes with the box class weighted
    10, and fine-tuning it with the default 5 pushed its decisions back to "shelf"."""
    import racklay.train as rt
    from racklay.checkpoint import save_checkpoint
    from racklay.model import ModelConfig, build_model
    from transfer.workflow import checkpoint_loss, finetune

    mcfg = ModelConfig(image_size=64, layout_size=64, encoder="resnet18", decoder="light", disc=False)
    init = save_checkpoint(tmp_path / "init.safetensors", build_model(mcfg), mcfg,
                           extra={"train_config": {"class_weights": [1, 3, 7], "iou_weight": 0.5, "gap_weight": 4}})
    assert checkpoint_loss(init) == {"class_weights": (1.0, 3.0, 7.0), "iou_weight": 0.5, "gap_weight": 4.0}
    seen = []
    monkeypatch.setattr(rt, "train", lambda cfg, transform=None: seen.append(cfg) or str(tmp_path / "run"))
    finetune(init, tiny_data / "real", tmp_path, name="ft", class_weights=given)
    assert seen[0].class_weights == expected and seen[0].init == str(init)
    assert seen[0].iou_weight == 0.5 and seen[0].gap_weight == 4.0
    finetune(init, tiny_data / "real", tmp_path, name="ft2", iou_weight=0.0, gap_weight=1.0)
    assert seen[1].iou_weight == 0.0 and seen[1].gap_weight == 1.0


def test_finetune_cli_mixes_synthetic_replay(tiny_data, tmp_path, monkeypatch):
    """`transfer finetune --replay ROOT --replay-ratio 0.5` reaches the trainer (the flag repeats
    to pool several sets); without the flags the fine-tune has no replay (TrainConfig's default)."""
    import racklay.train as rt
    from racklay.checkpoint import save_checkpoint
    from racklay.model import ModelConfig, build_model
    from transfer.cli import main

    mcfg = ModelConfig(image_size=64, layout_size=64, encoder="resnet18", decoder="light", disc=False)
    init = save_checkpoint(tmp_path / "init.safetensors", build_model(mcfg), mcfg)
    seen = []
    monkeypatch.setattr(rt, "train", lambda cfg, transform=None: seen.append(cfg) or str(tmp_path / "run"))
    monkeypatch.setattr("transfer.commands.finetune.print_run", lambda run: None)
    base = ["finetune", "--init", str(init), "--real", str(tiny_data / "real"), "--out", str(tmp_path / "ft")]
    assert main(base + ["--replay", str(tiny_data / "syn"), "--replay-ratio", "0.5"]) == 0
    assert main(base) == 0
    assert main(base + ["--replay", str(tiny_data / "syn"), "--replay", str(tiny_data / "real")]) == 0
    assert (seen[0].replay, seen[0].replay_ratio) == ((str(tiny_data / "syn"),), 0.5)
    assert seen[1].replay is None
    assert seen[2].replay == (str(tiny_data / "syn"), str(tiny_data / "real"))   # several sets pool


def test_compare_settings_keep_run_defining_training_options_only():
    """compare.json records the compare's own keep=True settings and, of its TrainConfig overrides,
    only those a resumed training run must keep: more workers may resume a compare, another batch
    size may not; an override TrainConfig does not have is refused before any run starts."""
    from racklay.config import RUN_DEFINING
    from transfer.compare import RESULT_KEYS, CompareConfig, validate

    base = CompareConfig(real="r", out="o", synthetic="s", train={"batch_size": 4, "workers": 0})
    assert set(base.settings()) == set(RESULT_KEYS) and "seeds" not in RESULT_KEYS and "out" not in RESULT_KEYS
    assert base.settings()["train"] == {"batch_size": 4} and "workers" not in RUN_DEFINING
    more_workers = CompareConfig(real="r", out="o", synthetic="s", train={"batch_size": 4, "workers": 2})
    other_batch = CompareConfig(real="r", out="o", synthetic="s", train={"batch_size": 8, "workers": 0})
    assert more_workers.settings() == base.settings() != other_batch.settings()
    with pytest.raises(ValueError, match=r"unknown training option\(s\) batchsize \(did you mean 'batch_size'\?\)"):
        validate(CompareConfig(real="r", out="o", synthetic="s", train={"batchsize": 4}))
