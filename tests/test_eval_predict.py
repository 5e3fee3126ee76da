"""racklay eval / predict / export: metrics plumbing, prediction outputs, bad inputs, ONNX parity.
Tiny models (64 px input, 32 px layouts) on the schematic toy dataset keep this fast."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from conftest import ground_truth_net, make_toy
from racklay import layout as L
from racklay.cli import main as racklay_main
from racklay.data import RackLayRoot, read_image
from racklay.predict import Predictor

IMG, S, R = 64, 32, 4


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    return make_toy(tmp_path_factory, n=10, seed=3, R=R, D=128)


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    from racklay.checkpoint import save_checkpoint
    from racklay.model import ModelConfig, RackLayNet

    torch.manual_seed(0)
    cfg = ModelConfig(R=R, image_size=IMG, layout_size=S, views=("top", "front"))
    model = RackLayNet(cfg).eval()
    path = tmp_path_factory.mktemp("ckpt") / "tiny.safetensors"
    save_checkpoint(path, model, cfg)
    return path


@pytest.fixture(scope="module")
def onnx_file(ckpt, tmp_path_factory):
    out = tmp_path_factory.mktemp("onnx") / "tiny.onnx"
    assert racklay_main(["export", "--weights", str(ckpt), "--onnx", str(out)]) == 0
    return out


def test_perfect_predictor_scores_one(toy):
    from racklay.evaluate import evaluate
    from racklay.model import ModelConfig
    from racklay.torchdata import RackLayDataset

    cfg = ModelConfig(R=R, image_size=IMG, layout_size=S)
    ds = RackLayDataset(toy, split="test", image_size=IMG, layout_size=S, R=R)
    net = ground_truth_net([ds[i] for i in range(len(ds))], 20.0 * torch.eye(3))   # confident and right
    res = evaluate((net, cfg), toy, split="test", batch_size=3, progress=False)
    for v in ("top", "front"):
        assert res[v]["images"] == len(ds)
        for k in ("rack", "box"):
            assert res[v]["paper"][k] == {"mIoU": 1.0, "pixel_precision": 1.0}
        for c in ("shelf", "box"):
            d = res[v]["dataset"][c]
            assert d["IoU"] == d["precision"] == d["recall"] == 1.0
            assert d["AP"] == pytest.approx(1.0)


def test_eval_cli_writes_json_and_table(toy, ckpt, tmp_path, capsys):
    out = tmp_path / "m.json"
    rc = racklay_main(["eval", "--weights", str(ckpt), "--data", str(toy), "--split", "test",
                       "--batch-size", "4", "--json", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "top rack | top box | front rack | front box" in text
    assert "| view | class | IoU | precision | recall | AP |" in text
    rep = json.loads(out.read_text())
    assert {"weights", "data", "split", "images", "model", "metrics"} <= set(rep)
    n_test = len(RackLayRoot(toy).split_ids("test"))
    assert rep["images"] == n_test and rep["split"] == "test" and rep["model"]["layout_size"] == S
    for v in ("top", "front"):
        m = rep["metrics"][v]
        assert set(m["paper"]) == {"rack", "box"}
        assert 0.0 <= m["paper"]["box"]["mIoU"] <= 1.0
        assert "AP" in m["dataset"]["box"]
        assert np.array(m["confusion"]).sum() == n_test * R * S * S


def test_eval_native_resolution_and_bad_split(toy, ckpt):
    from racklay.data import DataError
    from racklay.evaluate import evaluate

    res = evaluate(ckpt, toy, split="val", native=True, progress=False, with_probs=False)
    n = len(RackLayRoot(toy).split_ids("val"))
    assert np.array(res["top"]["confusion"]).sum() == n * R * 128 * 128
    assert "AP" not in res["top"]["dataset"]["box"]
    with pytest.raises(DataError, match="nosuch.txt"):
        evaluate(ckpt, toy, split="nosuch", progress=False)


def test_predict_folder_outputs_and_bad_files(toy, ckpt, tmp_path, capsys):
    src = tmp_path / "photos"
    src.mkdir()
    ds = RackLayRoot(toy)
    ids = ds.ids()[:2]
    import cv2

    cv2.imwrite(str(src / f"{ids[0]}.png"), cv2.cvtColor(ds.read_image(ids[0]), cv2.COLOR_RGB2BGR))
    big = cv2.resize(ds.read_image(ids[1]), (1000, 600))  # another size, as JPEG
    cv2.imwrite(str(src / f"{ids[1]}.jpg"), cv2.cvtColor(big, cv2.COLOR_RGB2BGR))
    (src / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    (src / "notes.txt").write_text("not an image")       # not a photo: skipped, said once
    (src / "labels.json").write_text("{}")
    (src / "fake.jpg").write_text("not an image")         # a photo's name: read, and its error named
    out = tmp_path / "pred"
    rc = racklay_main(["predict", str(src), "--weights", str(ckpt), "--out", str(out), "--layout-size", "128"])
    cap = capsys.readouterr()
    assert rc == 1
    errors = [line for line in cap.err.splitlines() if line.startswith("error:")]
    assert len(errors) == 2
    assert any("broken.png" in e for e in errors) and any("fake.jpg" in e for e in errors)
    assert "note: skipped 2 file(s) that are not photos (labels.json, notes.txt)" in cap.err
    assert "2 of 4 input(s) failed, 2 predicted" in cap.out
    # a folder of photos with a README predicts cleanly (exit 0)
    (src / "broken.png").unlink()
    (src / "fake.jpg").unlink()
    assert racklay_main(["predict", str(src), "--weights", str(ckpt), "--out", str(tmp_path / "p2")]) == 0
    # a 1x1 photo is predicted, with a warning naming it
    tiny = tmp_path / "tiny.png"
    cv2.imwrite(str(tiny), np.zeros((1, 1, 3), np.uint8))
    assert racklay_main(["predict", str(tiny), "--weights", str(ckpt), "--out", str(tmp_path / "p4")]) == 0
    assert f"warning: {tiny}: 1x1 pixels is far smaller than the model's" in capsys.readouterr().err
    # a non-image named on the command line is still an error, not skipped
    assert racklay_main(["predict", str(src / "notes.txt"), "--weights", str(ckpt), "--out", str(tmp_path / "p3")]) == 1
    pr = RackLayRoot(out)
    for sid in ids:
        for v in ("top", "front"):
            raw = np.load(pr.layout_path(v, sid))
            assert raw.shape == (R, 128, 128) and set(np.unique(raw)) <= {0, 115, 255}
            png = read_image(out / "png" / f"{sid}_{v}_shelf1.png")
            assert png.shape == (128, 128, 3)
        assert read_image(out / "figures" / f"{sid}.png").shape[0] > 100
        assert pr.read_meta(sid)["source"].endswith((".png", ".jpg"))
    assert not (out / "figures" / "broken.png").exists()
    # the output is a RackLay dataset that `racklay score` reads against the truth
    assert racklay_main(["score", "--pred", str(out), "--gt", str(toy)]) == 0
    assert "Paper protocol" in capsys.readouterr().out


@pytest.mark.slow
def test_predictor_any_size_and_bad_weights(ckpt, tmp_path):
    from racklay.predict import Predictor

    p = Predictor(ckpt)
    for shape in ((280, 470, 3), (37, 91, 3), (50, 60), (40, 40, 4)):
        out = p.predict(np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8))
        assert out["top"].shape == out["front"].shape == (R, S, S)
        assert out["probs"]["top"].shape == (R, 3, S, S)
        np.testing.assert_allclose(out["probs"]["front"].sum(axis=1), 1.0, atol=1e-5)
        assert (out["top"] == out["probs"]["top"].argmax(1)).all()
        assert out["grid"] == L.Grid(S, 8.0)
    with pytest.raises(ValueError, match="uint8"):
        p.predict(np.zeros((10, 10, 3), np.float32))
    # bf16 autocast: same shapes, nearly the same classes
    img = np.random.default_rng(1).integers(0, 256, (120, 200, 3), dtype=np.uint8)
    a, b = p.predict(img), Predictor(ckpt, precision="bf16").predict(img)
    assert b["probs"]["top"].dtype == np.float32
    assert (a["top"] == b["top"]).mean() > 0.95 and (a["front"] == b["front"]).mean() > 0.95
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"nope")
    with pytest.raises(ValueError, match="bad.safetensors"):
        Predictor(bad)
    assert racklay_main(["predict", str(tmp_path), "--weights", str(bad), "--out", str(tmp_path / "o")]) == 2
    bad_onnx = tmp_path / "bad.onnx"
    bad_onnx.write_bytes(b"\x08\x07garbage")
    with pytest.raises(ValueError, match="bad.onnx"):
        Predictor(bad_onnx)


@pytest.mark.parametrize("decoder", ["light", "struct"])
def test_bf16_predictor_keeps_its_weights_in_bf16_with_autocasts_own_logits(tmp_path, decoder):
    """In bf16 the loaded model keeps its convolution and linear weights in bf16 (autocast would
    cast them on every call) and gives, bit for bit, the logits bf16 autocast gives with fp32
    weights; fp32 keeps fp32 weights."""
    from racklay.checkpoint import load_model, save_checkpoint
    from racklay.model import ModelConfig, RackLayNet, fold_batchnorm

    torch.manual_seed(1)
    cfg = ModelConfig(R=2, image_size=(64, 128), layout_size=32, decoder=decoder)
    path = tmp_path / "m.safetensors"
    save_checkpoint(path, RackLayNet(cfg).eval(), cfg)
    p = Predictor(path, precision="bf16")
    convs = [m for m in p.model.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]
    assert convs and all(m.weight.dtype == torch.bfloat16 for m in convs)
    model = load_model(path)[0].eval()
    fold_batchnorm(model)
    model = model.to(memory_format=torch.channels_last)
    x = torch.randn(2, 3, 64, 128)
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        want = model(x.contiguous(memory_format=torch.channels_last))
    got = p.logits(x)
    for v in cfg.views:
        np.testing.assert_array_equal(got[v], want[v].float().numpy())
    assert all(m.weight.dtype == torch.float32 for m in Predictor(path, precision="fp32").model.modules()
               if isinstance(m, torch.nn.Conv2d))


def test_predictor_runs_channels_last_with_the_models_own_logits(ckpt):
    """The loaded model runs in oneDNN's layout (faster on CPU) and gives the logits the model gives
    in PyTorch's default layout; a wrapped in-training model keeps its layout in fp32."""
    from racklay.checkpoint import load_model

    def conv3x3(net):   # a weight whose two layouts differ
        return next(m.weight for m in net.modules() if isinstance(m, torch.nn.Conv2d) and m.kernel_size == (3, 3)
                    and m.groups == 1 and m.in_channels > 1)

    p = Predictor(ckpt)
    assert conv3x3(p.model).is_contiguous(memory_format=torch.channels_last)
    model, cfg, _ = load_model(ckpt)
    x = torch.randn(2, 3, IMG, IMG)
    with torch.inference_mode():
        want = model.eval()(x)
    got = p.logits(x)
    for v in cfg.views:
        np.testing.assert_allclose(got[v], want[v].numpy(), atol=1e-4)
    Predictor.from_model(model, cfg)
    assert conv3x3(model).is_contiguous() and not conv3x3(model).is_contiguous(memory_format=torch.channels_last)


def test_onnx_parity_and_backend(ckpt, onnx_file, toy, capsys):
    from racklay.checkpoint import load_model
    from racklay.export import parity
    from racklay.predict import Predictor

    model, cfg, _ = load_model(ckpt)
    res = parity(model, onnx_file, cfg)
    for v in cfg.views:
        assert res["max_abs_diff"][v] < 1e-3 * max(1.0, res["logit_scale"][v])
    image = RackLayRoot(toy).read_image(RackLayRoot(toy).ids()[0])
    a = Predictor(ckpt).predict(image)
    for b in (Predictor(onnx_file).predict(image), Predictor(ckpt, backend="onnx").predict(image)):
        for v in cfg.views:
            assert (a[v] == b[v]).mean() > 0.999
            np.testing.assert_allclose(a["probs"][v], b["probs"][v], atol=1e-4)


def test_onnx_metadata_is_the_checkpoint_config_and_read_strictly(ckpt, onnx_file, tmp_path):
    """The ONNX file stores `ModelConfig.to_dict` (the checkpoint serialiser) and reads it back
    equal; a key this version does not know (a newer exporter) is refused with one line naming
    the file and the key, not silently dropped."""
    import onnx

    from racklay.checkpoint import load_model
    from racklay.model import ModelConfig
    from racklay.onnx import ONNX_CONFIG_KEY

    _, cfg, _ = load_model(ckpt)
    assert Predictor(onnx_file).cfg == cfg
    proto = onnx.load(str(onnx_file))
    (entry,) = [p for p in proto.metadata_props if p.key == ONNX_CONFIG_KEY]
    assert json.loads(entry.value) == cfg.to_dict()
    assert ModelConfig.from_dict(json.loads(entry.value)) == cfg
    entry.value = json.dumps({**cfg.to_dict(), "from_the_future": 1})
    newer = tmp_path / "newer.onnx"
    onnx.save(proto, str(newer))
    with pytest.raises(ValueError, match=r"newer.onnx: .*from_the_future.*re-export") as e:
        Predictor(newer)
    assert "\n" not in str(e.value)


def test_predict_cli_onnx_matches_torch(ckpt, onnx_file, toy, tmp_path):
    img = RackLayRoot(toy).image_path(RackLayRoot(toy).ids()[0])
    outs = {}
    for name, extra in (("torch", ["--fp32"]), ("onnx", ["--backend", "onnx"])):
        o = tmp_path / name
        assert racklay_main(["predict", str(img), "--weights", str(ckpt), "--out", str(o),
                             "--no-figure", "--no-png"] + extra) == 0
        outs[name] = np.load(RackLayRoot(o).layout_path("top", img.stem))
    assert (outs["torch"] == outs["onnx"]).mean() > 0.999
    assert RackLayRoot(tmp_path / "onnx").read_meta(img.stem)["backend"] == "onnx"


def test_export_rejects_bad_file(tmp_path, capsys):
    bad = tmp_path / "x.safetensors"
    bad.write_bytes(b"\x00" * 64)
    assert racklay_main(["export", "--weights", str(bad), "--onnx", str(tmp_path / "y.onnx")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "x.safetensors" in err[0]
    assert not (tmp_path / "y.onnx").exists()


def test_precision_auto_resolution(monkeypatch, ckpt, onnx_file):
    """--precision auto (the CLI default) is bf16 only for torch on a CPU with native bf16;
    onnxruntime always runs fp32 and an explicit bf16 request for it is refused. Training speaks
    the same vocabulary (`amp`), reading the older `none` as fp32."""
    import racklay.precision as P
    from racklay.train import TrainConfig

    monkeypatch.setattr(P, "native_bf16", lambda: True)
    assert P.resolve_precision("auto") == "bf16" and P.resolve_precision("auto", backend="onnx") == "fp32"
    assert Predictor(ckpt, precision="auto").precision == "bf16"
    assert Predictor(onnx_file, precision="auto").precision == "fp32"
    monkeypatch.setattr(P, "native_bf16", lambda: False)
    assert Predictor(ckpt, precision="auto").precision == "fp32"
    with pytest.raises(ValueError, match="bf16 is for the torch backend"):
        Predictor(onnx_file, precision="bf16")
    with pytest.raises(ValueError, match="precision must be one of"):
        P.resolve_precision("fp16")
    assert TrainConfig(data="x", amp="none").amp == "fp32" and P.resolve_precision("none") == "fp32"
    with pytest.raises(ValueError, match="amp must be one of"):
        TrainConfig(data="x", amp="fp16")


def test_outputs_never_overwrite_ground_truth_and_bad_inputs_write_nothing(toy, ckpt, tmp_path, capsys):
    """eval --save-predictions into the dataset it scores, or predict into any dataset with splits,
    is refused before the model runs; an empty input folder is an error, not "0 predicted";
    export checks --image before writing the .onnx."""
    before = (toy / "topLayouts" / "top000000.npy").read_bytes()
    assert racklay_main(["eval", "--weights", str(ckpt), "--data", str(toy), "--save-predictions", str(toy)]) == 2
    assert "would overwrite its ground truth" in capsys.readouterr().err
    assert racklay_main(["predict", str(RackLayRoot(toy).image_path("000000")), "--weights", str(ckpt),
                         "--out", str(toy)]) == 2
    assert "holds a dataset with ground truth (splits found)" in capsys.readouterr().err
    assert (toy / "topLayouts" / "top000000.npy").read_bytes() == before
    empty = tmp_path / "empty"
    empty.mkdir()
    assert racklay_main(["predict", str(empty), "--weights", str(ckpt), "--out", str(tmp_path / "o")]) == 2
    assert "no photos to predict" in capsys.readouterr().err
    bad = tmp_path / "bad.png"
    bad.write_text("not a png")
    onnx = tmp_path / "m.onnx"
    assert racklay_main(["export", "--weights", str(ckpt), "--onnx", str(onnx), "--image", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.png" in err[0]
    assert not onnx.exists()


def test_shape_errors_name_the_file_that_is_wrong(toy, ckpt, tmp_path, capsys):
    """The odd file out is named, not whichever file happened to be read alongside it: a
    3-channel ground-truth file in `score` (not the good prediction beside it), a 3-channel top
    layout in `show` (not its good front layout), and an R=3 model on R=4 data in `eval` (the
    model, not a dataset file)."""
    import shutil

    from racklay.atomic import atomic_save_npy
    from racklay.checkpoint import save_checkpoint
    from racklay.model import ModelConfig, RackLayNet

    gt = tmp_path / "gt"
    shutil.copytree(toy, gt)
    pred = tmp_path / "pred"
    for d in ("topLayouts", "frontLayouts"):
        shutil.copytree(toy / d, pred / d)
    sid = RackLayRoot(gt).ids()[2]
    bad = RackLayRoot(gt).layout_path("top", sid)
    atomic_save_npy(bad, np.load(bad)[:3])
    assert racklay_main(["score", "--pred", str(pred), "--gt", str(gt)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: 3 shelf channels, expected R=4" in err and str(pred) not in err, err
    assert racklay_main(["show", str(gt), "--id", sid, "--out", str(tmp_path / "f.png")]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: 3 shelf channels, expected R=4" in err and "frontLayouts" not in err, err

    cfg = ModelConfig(R=3, image_size=IMG, layout_size=S)
    r3 = save_checkpoint(tmp_path / "r3.safetensors", RackLayNet(cfg), cfg)
    assert racklay_main(["eval", "--weights", str(r3), "--data", str(toy), "--split", "all"]) == 2
    err = capsys.readouterr().err
    assert f"{r3}: the model predicts R=3 shelves but the layouts in {toy} have R=4" in err, err


def test_a_full_disk_stops_predict_naming_the_file(toy, ckpt, tmp_path, capsys, monkeypatch):
    """Disk full while writing: one error naming the output file, and predict stops instead of
    trying (and failing) every remaining photo."""
    import errno

    import racklay.atomic as atomic

    calls = []

    def full(fd):
        calls.append(fd)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", full)
    out = tmp_path / "pred"
    rc = racklay_main(["predict", str(toy / "Images"), "--weights", str(ckpt), "--out", str(out), "--no-figure"])
    err = capsys.readouterr().err
    assert rc == 2 and len(calls) == 1
    line = [x for x in err.splitlines() if "error" in x]
    assert len(line) == 1 and str(out) in line[0] and "no space left on device" in line[0], err


def test_flip_averaged_predict_and_eval_say_so(ckpt, toy, tmp_path, capsys):
    """`--flip-average` in predict and eval: a mirrored photo is predicted as the mirror of the
    photo's prediction, the run is recorded (predict's meta, eval's JSON and title), and the onnx
    backend refuses it in one line."""
    import cv2

    root = RackLayRoot(toy)
    img = root.image_path(root.ids()[0])
    flipped = tmp_path / "mirror.png"
    cv2.imwrite(str(flipped), cv2.imread(str(img))[:, ::-1])
    o = tmp_path / "p"
    assert racklay_main(["predict", str(img), str(flipped), "--weights", str(ckpt), "--out", str(o),
                         "--no-figure", "--no-png", "--fp32", "--flip-average"]) == 0
    out = RackLayRoot(o)
    for v in ("top", "front"):
        a, b = np.load(out.layout_path(v, img.stem)), np.load(out.layout_path(v, "mirror"))
        assert (a == b[..., ::-1]).mean() > 0.999
    assert out.read_meta(img.stem)["flip_average"] is True
    assert "flip-averaged" in capsys.readouterr().out
    js = tmp_path / "e.json"
    assert racklay_main(["eval", "--weights", str(ckpt), "--data", str(toy), "--flip-average", "--json", str(js)]) == 0
    assert json.loads(js.read_text())["flip_average"] is True and "flip-averaged" in capsys.readouterr().out
    assert racklay_main(["analyze", str(img), "--weights", str(ckpt), "--out", str(tmp_path / "a"),
                         "--no-render", "--flip-average"]) == 0
    assert racklay_main(["predict", str(img), "--weights", str(ckpt), "--out", str(tmp_path / "q"),
                         "--backend", "onnx", "--flip-average"]) == 2
    assert "flip averaging is for the torch backend" in capsys.readouterr().err


def test_outputs_that_cannot_be_written_and_impossible_lengths_are_refused_before_any_work(
        toy, ckpt, tmp_path, capsys, monkeypatch):
    """An output that cannot be written (a file where a folder goes, a folder where a file goes)
    and a shelf length the grid cannot draw are one-line errors before the model runs; nothing is
    predicted or written. A folder's subfolders are said to be skipped; a dataset given as the
    photo folder is pointed to its Images/."""
    import racklay.predict as P

    ran = []
    monkeypatch.setattr(P.Predictor, "predict", lambda *a, **k: ran.append(1))
    photos = str(toy / "Images")
    afile = tmp_path / "afile"
    afile.write_text("")
    folder = tmp_path / "folder"
    folder.mkdir()
    cases = [
        (["predict", photos, "--weights", str(ckpt), "--out", str(afile)], f"{afile}: is a file, expected a folder"),
        (["predict", photos, "--weights", str(ckpt), "--out", str(afile / "sub")], "is a file"),
        (["predict", photos, "--weights", str(ckpt), "--out", str(tmp_path / "p"), "--shelf-length", "270"],
         "shelf length 270.0 m: outside what the 8 m, 32-pixel layout grid can draw"),
        (["predict", photos, "--weights", str(ckpt), "--out", str(tmp_path / "p"), "--shelf-length", "1e-9"],
         "metres, not centimetres"),
        (["eval", "--weights", str(ckpt), "--data", str(toy), "--json", str(folder)],
         f"{folder}: is a folder, expected a file (--json file)"),
        (["score", "--pred", str(toy), "--gt", str(toy), "--json", str(folder)], "is a folder, expected a file"),
        (["check-data", str(toy), "--json", str(folder)], "is a folder, expected a file"),
        # wrong-kind inputs say so (they read "not found"): a folder for the weights, a file for the data
        (["eval", "--weights", str(folder), "--data", str(toy)], f"{folder}: --weights is a folder, not a weights file"),
        (["eval", "--weights", str(ckpt), "--data", str(afile)], f"{afile}: is a file, not a dataset folder"),
        (["show", str(afile), "--index", "0", "--out", str(tmp_path / "s.png")], "is a file, not a dataset folder"),
        (["calibrate", "--weights", str(ckpt), "--data", str(toy), "--split", "val", "--out",
          str(afile / "c.safetensors")], "cannot write the calibrated checkpoint there"),
    ]
    for argv, want in cases:
        assert racklay_main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and want in err[0], (argv, err)
    assert not ran and not (tmp_path / "p").exists() and list(folder.iterdir()) == []

    # a subfolder is not searched, and the user is told so; a dataset points to its Images/
    src = tmp_path / "src"
    (src / "nested").mkdir(parents=True)
    assert racklay_main(["predict", str(src), "--weights", str(ckpt), "--out", str(tmp_path / "q")]) == 2
    assert "(empty folder?)" in capsys.readouterr().err
    assert racklay_main(["predict", str(toy), "--weights", str(ckpt), "--out", str(tmp_path / "q")]) == 2
    assert f"its photos are in {toy / 'Images'}" in capsys.readouterr().err
    monkeypatch.undo()
    (src / "a.png").write_bytes((toy / "Images" / sorted((toy / "Images").iterdir())[0].name).read_bytes())
    assert racklay_main(["predict", str(src), "--weights", str(ckpt), "--out", str(tmp_path / "q"),
                         "--no-figure"]) == 0
    assert "note: skipped 1 subfolder(s), not searched (name them to predict their photos) (nested)" \
        in capsys.readouterr().err


def test_saved_predictions_are_at_the_dataset_size_and_score_as_eval_native(toy, ckpt, tmp_path):
    """eval --save-predictions wrote the model's 32² layouts, which `racklay score` refused against
    the 128² dataset it had just evaluated; saved at the dataset's size they score exactly as
    `eval --native` does."""
    import json

    pred = tmp_path / "pred"
    assert racklay_main(["eval", "--weights", str(ckpt), "--data", str(toy), "--fp32",
                         "--save-predictions", str(pred), "--no-progress"]) == 0
    assert racklay_main(["eval", "--weights", str(ckpt), "--data", str(toy), "--fp32", "--native",
                         "--json", str(tmp_path / "e.json"), "--no-progress"]) == 0
    pr = RackLayRoot(pred)
    assert np.load(pr.layout_path("front", pr.layout_ids("front")[0])).shape == (R, 128, 128)
    assert racklay_main(["score", "--pred", str(pred), "--gt", str(toy), "--json", str(tmp_path / "s.json")]) == 0
    ev, sc = (json.loads((tmp_path / f).read_text()) for f in ("e.json", "s.json"))
    for v in ("top", "front"):
        for c in ("background", "shelf", "box"):
            assert sc[v]["dataset"][c]["IoU"] == pytest.approx(ev["metrics"][v]["dataset"][c]["IoU"])


def test_rack_box_reads_the_outlined_rack_and_says_so(ckpt, toy, tmp_path, capsys):
    """`predict --rack-box X0,Y0,X1,Y1`: the model reads the photo cropped to the box (grown by
    the margin and to the model's aspect, inside the photo), exactly as if the user had cropped
    it; the sample's image is that crop and its meta records box and crop; a box that misses a
    photo is a one-line error naming it, and a malformed box is refused before any work."""
    import cv2

    from racklay.predict import RACK_BOX_MARGIN, rack_crop

    root = RackLayRoot(toy)
    img = root.image_path(root.ids()[0])
    photo = read_image(img)
    H, W = photo.shape[:2]
    box = (0.30 * W, 0.25 * H, 0.70 * W, 0.45 * H)
    c = rack_crop(box, W, H, 1.0)                       # the tiny model's input is square
    assert c[0] <= box[0] and c[1] <= box[1] and c[2] >= box[2] and c[3] >= box[3]
    assert 0 <= c[0] < c[2] <= W and 0 <= c[1] < c[3] <= H
    assert abs((c[2] - c[0]) / (c[3] - c[1]) - 1.0) < 0.1
    assert (c[2] - c[0]) >= (box[2] - box[0]) * (1 + 2 * RACK_BOX_MARGIN) - 1
    # a box at the photo's edge is shifted inside, not padded
    assert rack_crop((0, 0, 10, 10), W, H, 2.0)[:2] == (0, 0)

    cropped = tmp_path / "cropped.png"
    cv2.imwrite(str(cropped), cv2.cvtColor(photo[c[1]:c[3], c[0]:c[2]], cv2.COLOR_RGB2BGR))
    o1, o2 = tmp_path / "boxed", tmp_path / "by_hand"
    arg = ",".join(f"{v:g}" for v in box)
    assert racklay_main(["predict", str(img), "--weights", str(ckpt), "--out", str(o1), "--fp32",
                         "--no-figure", "--no-png", "--rack-box", arg]) == 0
    assert "read in the rack box" in capsys.readouterr().out
    assert racklay_main(["predict", str(cropped), "--weights", str(ckpt), "--out", str(o2), "--fp32",
                         "--no-figure", "--no-png"]) == 0
    a, b = RackLayRoot(o1), RackLayRoot(o2)
    for v in ("top", "front"):
        np.testing.assert_array_equal(np.load(a.layout_path(v, img.stem)), np.load(b.layout_path(v, "cropped")))
    meta = a.read_meta(img.stem)
    assert meta["crop_px"] == list(c) and meta["rack_box_px"] == pytest.approx(list(box), abs=1e-3)
    assert meta["photo_size"] == [W, H] and meta["input_size"] == [c[2] - c[0], c[3] - c[1]]
    np.testing.assert_array_equal(a.read_image(img.stem), photo[c[1]:c[3], c[0]:c[2]])

    capsys.readouterr()
    assert racklay_main(["predict", str(img), "--weights", str(ckpt), "--out", str(tmp_path / "off"),
                         "--rack-box", f"{W + 5},0,{W + 50},10"]) == 1
    err = capsys.readouterr().err
    assert f"{img}: rack box" in err and "lies outside" in err and not (tmp_path / "off").exists()
    # analyze takes the same box, and names the photo a box misses
    assert racklay_main(["analyze", str(img), "--weights", str(ckpt), "--out", str(tmp_path / "a1"),
                         "--no-render", "--format", "none", "--rack-box", arg]) == 0
    assert racklay_main(["analyze", str(img), "--weights", str(ckpt), "--out", str(tmp_path / "a2"),
                         "--no-render", "--format", "none", "--rack-box", f"0,{H + 1},5,{H + 9}"]) == 1
    assert f"{img}: rack box" in capsys.readouterr().err
    assert racklay_main(["analyze", "--layouts", str(toy), "--out", str(tmp_path / "b"), "--rack-box", arg]) == 2
    assert "--rack-box tells a model which rack to read" in capsys.readouterr().err
    for bad in ("1,2,3", "5,5,1,1", "a,b,c,d"):
        with pytest.raises(SystemExit):
            racklay_main(["predict", str(img), "--weights", str(ckpt), "--out", str(tmp_path / "x"),
                          "--rack-box", bad])
        assert "--rack-box" in capsys.readouterr().err


def test_table1_scoring_refuses_a_test_set_of_another_recipe(tmp_path, monkeypatch):
    """release_targets (and table1_cpu.sh's scoring through it) renders the WareSynth test set of
    the recipe it is told, and refuses a folder that holds another recipe's renders instead of
    scoring the model on them; a folder of the same recipe is used as it is."""
    import subprocess

    from bench.accuracy.release_targets import ensure

    root = tmp_path / "complex-test"
    (root / "splits").mkdir(parents=True)
    (root / "splits" / "test.txt").write_text("000000\n")
    (root / "waresynth.json").write_text(json.dumps({"recipe": {"name": "complex"}, "n": 2000, "seed": 2027}))
    monkeypatch.setattr(subprocess, "run", lambda *a, **k: pytest.fail(f"rendered: {a}"))
    with pytest.raises(SystemExit) as e:
        ensure(root, ["--recipe", "complex_paper", "--n", "2000", "--seed", "2027"])
    msg = str(e.value)
    assert str(root / "waresynth.json") in msg and "'complex'" in msg and "'complex_paper'" in msg
    ensure(root, ["--recipe", "complex", "--n", "2000", "--seed", "2027"])   # there already: nothing rendered


def test_struct_model_draws_its_layouts_at_any_size(toy, ckpt, tmp_path):
    """A struct model's structure is metric and continuous: at a dataset's D it is drawn at D (its
    shelf as long as the structure says, to a pixel of D), not the S x S layout upsampled (to a pixel
    of S); `drawing_at` restores the trained size, eval --native and predict --layout-size use it,
    and a dense model keeps its size (callers resize)."""
    from racklay.checkpoint import save_checkpoint
    from racklay.evaluate import evaluate
    from racklay.model import ModelConfig, RackLayNet

    torch.manual_seed(2)
    cfg = ModelConfig(R=R, image_size=IMG, layout_size=S, decoder="struct")
    path = tmp_path / "struct.safetensors"
    save_checkpoint(path, RackLayNet(cfg).eval(), cfg)
    p = Predictor(path)
    image = RackLayRoot(toy).read_image(RackLayRoot(toy).ids()[0])
    coarse = p.predict(image)
    with p.drawing_at(128) as drawn:
        assert drawn and p.layout_size == 128
        fine = p.predict(image)
        length = p.structures(p.prepare(image))["top"]["length"][0].float().numpy()
    assert p.layout_size == S and fine["grid"].size == 128 and fine["top"].shape == (R, 128, 128)
    shelves = np.flatnonzero(fine["top"].reshape(R, -1).max(-1) > 0)
    assert len(shelves)
    for k in shelves:          # a shelf is centred: its columns come in pairs, so within 2 pixels
        cols = lambda lay: np.count_nonzero(lay[k].max(0) > 0)                # noqa: E731
        assert abs(cols(fine["top"]) * 8.0 / 128 - length[k]) <= 2 * 8.0 / 128
        assert abs(cols(coarse["top"]) * 8.0 / S - length[k]) <= 2 * 8.0 / S
    # the two agree but where an edge falls between S's pixel boundaries
    up = L.resize_layouts(coarse["top"], 128)
    assert 0.9 < np.mean(up == fine["top"]) < 1.0
    res = evaluate(p, toy, split="val", native=True, progress=False, with_probs=False)
    n = len(RackLayRoot(toy).split_ids("val"))
    assert np.array(res["top"]["confusion"]).sum() == n * R * 128 * 128 and p.layout_size == S
    out = tmp_path / "pred"
    assert racklay_main(["predict", str(RackLayRoot(toy).image_path(RackLayRoot(toy).ids()[0])),
                         "--weights", str(path), "--out", str(out), "--layout-size", "128"]) == 0
    sid = RackLayRoot(out).ids()[0]
    np.testing.assert_array_equal(RackLayRoot(out).read_layouts("top", sid, R=R), fine["top"])
    # an ONNX graph has its size built in; a dense model predicts at its trained size
    onnx = Predictor(path, backend="onnx")
    assert not onnx.draw_at(128) and onnx.layout_size == S
    dense = Predictor(ckpt)
    assert not dense.draw_at(128) and dense.layout_size == S
    with pytest.raises(ValueError, match="only a struct model draws"):
        dense.model.set_draw_size(128)
