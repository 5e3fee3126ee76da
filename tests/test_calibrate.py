"""Decision calibration (racklay/calibrate.py, `racklay calibrate`, `ModelConfig.decision_bias`):
the fit recovers a known under-calling of boxes, the Predictor applies the stored biases, and the
CLI writes a checkpoint that carries them. Tiny models on the schematic toy dataset."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import ground_truth_net
from racklay.calibrate import DiffHistogram, fit_decision_bias
from racklay.checkpoint import load_checkpoint, save_checkpoint
from racklay.cli import main as racklay_main
from racklay.model import ModelConfig, RackLayNet
from racklay.predict import Predictor, decide
from racklay.torchdata import RackLayDataset
from racklay.toy import build_toy_dataset

IMG, S, R = 64, 32, 4
#: logits per ground-truth class of a model that ranks boxes right but calls them "shelf"
UNDER_CALLING = {0: (2.0, 0.0, -1.0), 1: (0.0, 3.0, 0.0), 2: (0.0, 2.0, 1.0)}


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    root = tmp_path_factory.mktemp("toy")
    build_toy_dataset(root, n=10, seed=5, R=R, D=64)
    return root


def _under_calling_predictor(toy, split="val", bias=None):
    cfg = ModelConfig(R=R, image_size=IMG, layout_size=S, decision_bias=bias)
    ds = RackLayDataset(toy, split=split, image_size=IMG, layout_size=S, R=R)
    lut = [UNDER_CALLING[k] for k in range(3)]
    return Predictor.from_model(ground_truth_net([ds[i] for i in range(len(ds))], lut), cfg), ds


def test_fit_recovers_box_bias_and_predictor_applies_it(toy):
    pred, ds = _under_calling_predictor(toy)
    fits = fit_decision_bias(pred, toy, split="val", batch_size=2, progress=False)
    assert [f.view for f in fits] == ["top", "front"]
    for f in fits:
        assert f.before["box_iou"] == 0.0                       # plain argmax never says "box"
        assert f.after["box_iou"] == pytest.approx(100.0) and f.after["shelf_iou"] == pytest.approx(100.0)
        b0, b1, b2 = f.bias
        assert b0 == 0.0 and 1.0 < b2 - b1 < 2.0 and b1 < 3.0    # box wins where it should, only there
    biased, _ = _under_calling_predictor(toy, bias={f.view: f.bias for f in fits})
    classes, probs = biased.predict_batch(torch.stack([ds[i]["image"] for i in range(len(ds))]))
    for v in ("top", "front"):
        gt = np.stack([ds[i][v].numpy() for i in range(len(ds))])
        assert (classes[v] == gt).all()
        # probabilities stay the model's own
        raw, _ = pred.predict_batch(torch.stack([ds[i]["image"] for i in range(len(ds))]))
        assert (raw[v] != classes[v]).any()


def test_histogram_scores_match_direct_iou():
    rng = np.random.default_rng(0)
    logits = rng.normal(0, 2, size=(3, 2, 3, 16, 16)).astype(np.float32)
    gt = rng.integers(0, 3, size=(3, 2, 16, 16))
    h = DiffHistogram()
    h.update(logits, gt)
    for bias in (None, (0.0, 0.5, 1.25)):
        cls = decide(logits, bias)
        got = h.scores(bias)
        for k, name in ((1, "shelf_iou"), (2, "box_iou")):
            inter = ((cls == k) & (gt == k)).sum()
            union = ((cls == k) | (gt == k)).sum()
            # bins are 1/16 wide: only pixels within a bin of a decision boundary may differ
            assert got[name] == pytest.approx(100 * inter / union, abs=2.0)


def test_config_rejects_bad_bias():
    with pytest.raises(ValueError, match="does not predict"):
        ModelConfig(views=("top",), decision_bias={"front": [0, 0, 1]})
    with pytest.raises(ValueError, match="3 finite numbers"):
        ModelConfig(decision_bias={"top": [0, 1]})
    with pytest.raises(ValueError, match="3 finite numbers"):
        ModelConfig(decision_bias={"top": [0, math.nan, 1]})
    cfg = ModelConfig(decision_bias={"top": [0, -0.5, 1]})
    assert ModelConfig.from_dict(cfg.to_dict()).decision_bias == {"top": (0.0, -0.5, 1.0)}


def test_cli_writes_calibrated_checkpoint(toy, tmp_path, capsys):
    torch.manual_seed(0)
    cfg = ModelConfig(R=R, image_size=IMG, layout_size=S)
    src = tmp_path / "tiny.safetensors"
    save_checkpoint(src, RackLayNet(cfg).eval(), cfg, extra={"epoch": 3})
    out = tmp_path / "cal.safetensors"
    assert racklay_main(["calibrate", "--weights", str(src), "--data", str(toy), "--split", "val",
                         "--out", str(out), "--json", str(tmp_path / "fit.json")]) == 0
    text = capsys.readouterr().out
    assert "box IoU" in text and "calibrated checkpoint written" in text
    ck = load_checkpoint(out)
    assert set(ck.cfg.decision_bias) == {"top", "front"}
    assert ck.meta["epoch"] == 3 and ck.meta["calibration"]["split"] == "val"
    # same weights; the calibrated predictor decides with the stored biases
    a, b = Predictor(src), Predictor(out)
    x = torch.stack([RackLayDataset(toy, split="test", image_size=IMG, layout_size=S, R=R)[0]["image"]])
    la, lb = a.logits(x), b.logits(x)
    classes, _ = b.predict_batch(x)
    for v in ("top", "front"):
        np.testing.assert_array_equal(la[v], lb[v])
        np.testing.assert_array_equal(classes[v], decide(lb[v], ck.cfg.decision_bias[v]))
    # the input is never overwritten
    assert racklay_main(["calibrate", "--weights", str(src), "--data", str(toy), "--out", str(src)]) != 0
    assert "must differ" in capsys.readouterr().err


def test_onnx_export_keeps_the_biases(tmp_path):
    pytest.importorskip("onnxruntime")
    torch.manual_seed(1)
    cfg = ModelConfig(R=R, image_size=IMG, layout_size=S, decision_bias={"top": (0, 0.5, 2.0), "front": (0, 0, 1.5)})
    src = tmp_path / "cal.safetensors"
    save_checkpoint(src, RackLayNet(cfg).eval(), cfg)
    onnx = tmp_path / "cal.onnx"
    assert racklay_main(["export", "--weights", str(src), "--onnx", str(onnx)]) == 0
    a, b = Predictor(src), Predictor(onnx)
    assert b.cfg.decision_bias == a.cfg.decision_bias
    x = torch.randn(1, 3, IMG, IMG)
    ca, _ = a.predict_batch(x)
    cb, _ = b.predict_batch(x)
    for v in ("top", "front"):
        assert (ca[v] == cb[v]).mean() > 0.99
