import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import make_toy
from racklay.cli import main
from racklay.data import RackLayRoot


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    return make_toy(tmp_path_factory, n=8, seed=2, D=64)


@pytest.mark.parametrize("prog", ["racklay", "transfer", "annotate"])
def test_console_scripts_have_help(prog):
    exe = shutil.which(prog) or str(__import__("pathlib").Path(sys.executable).parent / prog)
    out = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "usage" in out.stdout


def test_check_data_clean_and_dirty(toy, tmp_path, capsys):
    assert main(["check-data", str(toy), "--json", str(tmp_path / "r.json")]) == 0
    assert json.loads((tmp_path / "r.json").read_text())["ok"] is True
    bad = tmp_path / "bad"
    shutil.copytree(toy, bad)
    a = np.load(bad / "topLayouts" / "top000000.npy")
    a[0, 0, 0] = 114
    np.save(bad / "topLayouts" / "top000000.npy", a)
    capsys.readouterr()
    assert main(["check-data", str(bad)]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[0].endswith("(allowed: 0, 115, 255)") and "top000000.npy" in out[0]
    assert "1 problem(s)" in out[-1]


def test_score_gt_against_itself_is_perfect(toy, tmp_path, capsys):
    assert main(["score", "--pred", str(toy), "--gt", str(toy), "--json", str(tmp_path / "s.json")]) == 0
    res = json.loads((tmp_path / "s.json").read_text())
    assert res["top"]["paper"]["box"]["mIoU"] == 1.0
    assert res["front"]["dataset"]["shelf"]["IoU"] == 1.0
    assert "pixel precision" in capsys.readouterr().out


def test_score_missing_ground_truth_is_one_line_error(toy, tmp_path, capsys):
    pred = RackLayRoot(tmp_path / "pred")
    pred.write_sample("777777", top=np.zeros((4, 64, 64), np.uint8))
    assert main(["score", "--pred", str(pred.root), "--gt", str(toy)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "top777777.npy" in err[0]


def test_score_missing_prediction_is_an_error_not_a_smaller_denominator(toy, tmp_path, capsys):
    pred = tmp_path / "pred"
    shutil.copytree(toy, pred)
    (pred / "topLayouts" / "top000002.npy").unlink()
    capsys.readouterr()
    # every predicted id: 000002 has a front prediction but no top one
    assert main(["score", "--pred", str(pred), "--gt", str(toy)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "top000002.npy: prediction missing" in err[0]
    # a split: every id of the split needs a prediction
    ids = RackLayRoot(toy).split_ids("train")
    for sid in ids[:2]:
        for view, pre in (("topLayouts", "top"), ("frontLayouts", "front")):
            (pred / view / f"{pre}{sid}.npy").unlink(missing_ok=True)
    assert main(["score", "--pred", str(pred), "--gt", str(toy), "--split", "train"]) == 2
    assert "prediction missing (and 1 more)" in capsys.readouterr().err


def test_unwritable_output_is_one_line_error(toy, tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert main(["score", "--pred", str(toy), "--gt", str(toy), "--json", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path) in err[0]
    assert main(["show", str(toy), "--index", "0", "--out", str(afile / "fig.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(afile) in err[0] and "Traceback" not in err[0]


def test_show_writes_figure(toy, tmp_path):
    out = tmp_path / "fig.png"
    assert main(["show", str(toy), "--index", "1", "--out", str(out)]) == 0
    from PIL import Image
    w, h = Image.open(out).size
    assert w > 600 and h > 300
    assert main(["show", str(toy), "--index", "99", "--out", str(out)]) == 2


def test_racklay_demo_says_where_the_demo_went(capsys):
    from racklay.cli import main

    assert main(["demo", "--quick"]) == 2
    err = capsys.readouterr().err
    assert "transfer demo --quick" in err and err.count("\n") == 1


def test_every_command_that_loops_over_images_takes_no_progress(monkeypatch):
    """Scripts pass --no-progress to any of them (it was refused by predict, eval, calibrate and
    check-data); a bar is drawn only on a terminal."""
    from racklay.cli import build_parser
    from racklay.commands import show_progress

    p = build_parser()
    for argv in (["synth", "--n", "2", "--out", "o"], ["predict", "x.jpg", "--out", "o"], ["eval", "--data", "d"],
                 ["calibrate", "--data", "d", "--out", "c.safetensors"], ["check-data", "d"]):
        args = p.parse_args(argv + ["--no-progress"])
        assert args.no_progress is True
        monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
        assert not show_progress(args) and show_progress(p.parse_args(argv))
        monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
        assert not show_progress(p.parse_args(argv))
    assert p.parse_args(["train", "--data", "d", "--no-progress"]).progress is False
