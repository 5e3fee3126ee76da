"""racklay distill: a narrower struct student learns its teacher's structures, reproducibly, and
refuses what it cannot use with one line."""
from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from conftest import make_toy
from racklay.checkpoint import load_checkpoint, load_model, save_checkpoint
from racklay.cli import main as cli_main
from racklay.distill import DistillConfig, distill, split_spec, teacher_pass
from racklay.model import ModelConfig, RackLayNet
from racklay.structure import distill_structure_loss


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A toy dataset and a small struct teacher with a gap output whose per-position outputs vary
    from image to image (its heads perturbed from the flat prior a fresh model starts at)."""
    data = make_toy(tmp_path_factory, n=10, seed=4, R=2, D=64)
    cfg = ModelConfig(R=2, image_size=(64, 128), layout_size=32, decoder="struct", struct_gap=True)
    torch.manual_seed(0)
    teacher = RackLayNet(cfg).eval()
    with torch.no_grad():
        for dec in teacher.decoders.values():
            for head in (dec.pos_head, dec.gap_head, dec.shelf_head):
                head.weight.normal_(0, 0.3)
    path = tmp_path_factory.mktemp("teacher") / "teacher.safetensors"
    save_checkpoint(path, teacher, cfg)
    return data, path


def _gap_to_teacher(student_path, teacher_path, data) -> float:
    """The distillation loss of a checkpoint against the teacher on the toy set's test images, less
    the teacher's against itself (the floor soft targets leave: their entropy)."""
    from racklay.distill import read_images, resolve_specs

    teacher, tcfg, _ = load_model(teacher_path)
    student, _, _ = load_model(student_path)
    images = read_images(resolve_specs([f"{data}:test"]), tcfg.input_hw, tcfg.letterbox, 0, 0, False)
    feats, targets = teacher_pass(teacher, images, (2, 3, 4), False)
    with torch.no_grad():
        f = [None, None] + [feats[k].float() for k in (2, 3, 4)]
        loss = sum(distill_structure_loss(v, st, targets[v]) for v, st in student.structures(f).items())
        return float(loss - sum(distill_structure_loss(v, targets[v], targets[v]) for v in targets))


def test_student_learns_the_teachers_structures_reproducibly(setup, tmp_path):
    data, teacher = setup
    kw = dict(teacher=str(teacher), data=(f"{data}:train",), photos=(f"{data}:val",), struct_width=8, steps=80,
              batch_size=8, lr=3e-3, warmup_steps=10, seed=1)
    logs = []
    out = distill(DistillConfig(out=str(tmp_path / "a.safetensors"), **kw), log=logs.append)
    ck = load_checkpoint(out)
    assert (ck.cfg.struct_width, ck.cfg.struct_fuse_k, ck.cfg.struct_fine, ck.cfg.struct_gap) == (8, 1, False, True)
    t = load_checkpoint(teacher).section("model")
    s = ck.section("model")
    assert all(torch.equal(s[k], v) for k, v in t.items() if k.startswith("encoder."))   # the teacher's encoder
    assert ck.meta["distilled_from"]["file"] == "teacher.safetensors" and ck.meta["steps"] == 80
    assert any("photo samples" in line for line in logs)
    # on images it never saw, the trained student is much closer to the teacher than a fresh one
    fresh = distill(DistillConfig(out=str(tmp_path / "fresh.safetensors"), **{**kw, "steps": 1, "lr": 1e-9}))
    assert _gap_to_teacher(out, teacher, data) < 0.5 * _gap_to_teacher(fresh, teacher, data)
    again = load_checkpoint(distill(DistillConfig(out=str(tmp_path / "b.safetensors"), **kw))).section("model")
    assert all(torch.equal(again[k], v) for k, v in s.items())                        # same seed, same student
    # one trunk for both views: a smaller student, which also learns the teacher's structures
    joint = distill(DistillConfig(out=str(tmp_path / "joint.safetensors"), **{**kw, "struct_joint": True}))
    jk = load_checkpoint(joint)
    assert jk.cfg.struct_joint and not any(k.startswith("decoders.front.fuse") for k in jk.section("model"))
    assert len(jk.section("model")) < len(s)
    assert _gap_to_teacher(joint, teacher, data) < 0.5 * _gap_to_teacher(fresh, teacher, data)


def test_pruned_student_starts_from_the_teachers_own_channels(setup, tmp_path):
    """`--init pruned`: cut to the teacher's own width and kernel, the student computes exactly the
    teacher's structures (every channel kept, in order); cut narrower, it holds the teacher's
    weights of the channels with the largest batch-norm scales."""
    from racklay.distill import load_teacher, student_for

    data, path = setup
    teacher, tcfg, _ = load_teacher(str(path))
    x = torch.rand(3, 3, *tcfg.input_hw)
    want = teacher.structures(teacher.encoder(x))
    cfg = DistillConfig(out=str(tmp_path / "s.safetensors"), data=(str(data),), init="pruned",
                        struct_width=tcfg.struct_width, struct_fuse_k=tcfg.struct_fuse_k)
    same, _ = student_for(teacher, tcfg, cfg)
    got = same.eval().structures(same.encoder(x))
    for view in want:
        for k in ("presence", "length", "centre", "box", "gap"):
            torch.testing.assert_close(got[view][k], want[view][k], rtol=1e-4, atol=1e-4)
    narrow, _ = student_for(teacher, tcfg, replace(cfg, struct_width=8, struct_fuse_k=1))
    src, dst = teacher.decoders["front"], narrow.decoders["front"]
    keep = src.fuse[1].weight.abs().topk(8).indices.sort().values
    torch.testing.assert_close(dst.fuse[1].weight, src.fuse[1].weight[keep])
    torch.testing.assert_close(dst.fuse[0].weight[..., 0, 0], src.fuse[0].weight[keep].sum((2, 3)))
    torch.testing.assert_close(dst.red32[0].weight, src.red32[0].weight)
    with pytest.raises(ValueError, match="wider than the teacher"):
        student_for(teacher, tcfg, replace(cfg, struct_width=tcfg.struct_width + 8))
    with pytest.raises(ValueError, match="struct-joint"):
        student_for(teacher, tcfg, replace(cfg, struct_joint=True))


def test_a_pruned_student_of_a_teacher_with_a_back_interval_keeps_it(setup, tmp_path):
    """A teacher with the top view's back interval (`struct_back`): the student has one too, and cut
    to the teacher's width it computes the teacher's back fields; the distillation loss reaches them."""
    from racklay.distill import student_for

    data, _ = setup
    tcfg = ModelConfig(R=2, image_size=(64, 128), layout_size=32, decoder="struct", struct_back=True)
    torch.manual_seed(0)
    teacher = RackLayNet(tcfg).eval()
    with torch.no_grad():
        teacher.decoders["top"].back_head.weight.normal_(0, 0.5)
    x = torch.rand(2, 3, 64, 128)
    want = teacher.structures(teacher.encoder(x))["top"]
    cfg = DistillConfig(out=str(tmp_path / "s.safetensors"), data=(str(data),), init="pruned",
                        struct_width=tcfg.struct_width, struct_fuse_k=tcfg.struct_fuse_k)
    student, _ = student_for(teacher, tcfg, cfg)
    got = student.eval().structures(student.encoder(x))["top"]
    for k in ("back", "back_near", "back_far"):
        torch.testing.assert_close(got[k], want[k], rtol=1e-4, atol=1e-4)
    fresh, _ = student_for(teacher, tcfg, replace(cfg, init="random"))
    st = fresh.train().structures(fresh.encoder(x))["top"]
    distill_structure_loss("top", st, {k: v.detach() for k, v in want.items()}).backward()
    assert fresh.decoders["top"].back_head.weight.grad.abs().sum() > 0


def test_distill_refuses_what_it_cannot_use(setup, tmp_path, tmp_path_factory, capsys):
    data, teacher = setup
    light = tmp_path / "light.safetensors"
    cfg = ModelConfig(R=2, image_size=(64, 128), layout_size=32, decoder="light")
    save_checkpoint(light, RackLayNet(cfg).eval(), cfg)
    cases = [(["--teacher", str(light), "--data", str(data)], f"{light}: has the light decoder"),
             (["--teacher", str(teacher), "--data", str(tmp_path / "none")], "dataset folder not found"),
             (["--teacher", str(teacher), "--data", f"{data}:nosuch"], "nosuch"),
             (["--teacher", str(teacher)], "give --data (renders) and/or --photos"),
             (["--teacher", str(teacher), "--data", str(data), "--out", str(tmp_path / "s.pt")], "must be a .safetensors"),
             (["--teacher", str(teacher), "--data", str(data), "--struct-fuse-k", "2"], "invalid choice")]
    for args, msg in cases:
        if "--out" not in args:
            args = [*args, "--out", str(tmp_path / "s.safetensors")]
        try:
            rc = cli_main(["distill", *args])
        except SystemExit as e:      # argparse's own checks
            rc = e.code
        assert rc == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert msg in err[-1], (args, err)
    assert not (tmp_path / "s.safetensors").exists()
    assert split_spec("/a/b:val") == ("/a/b", "val") and split_spec("/a/b") == ("/a/b", "train")


def test_gap_weight_makes_a_missed_teacher_gap_cost_more():
    """A student that misses the one position the teacher calls a gap costs more with a gap weight;
    one that matches the teacher costs the same with any weight."""
    N, R, T = 1, 1, 16
    gap = torch.full((N, R, T), -6.0)
    gap[..., 8] = 6.0
    teacher = {"presence": torch.full((N, R), 6.0), "length": torch.ones(N, R), "extent": torch.ones(N, R),
               "half": torch.full((N, R), 0.4), "centre": torch.zeros(N, R), "box_raw": torch.full((N, R, T), 4.0),
               "gap": gap, "height": torch.full((N, R, T), 0.5)}
    missed = {**teacher, "gap": torch.full((N, R, T), -6.0)}
    a, b = (distill_structure_loss("front", missed, teacher, w) for w in (1.0, 5.0))
    assert b > a + 0.5
    same = [distill_structure_loss("front", teacher, teacher, w) for w in (1.0, 5.0)]
    assert abs(float(same[1] - same[0])) < 0.05
