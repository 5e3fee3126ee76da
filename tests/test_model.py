"""RackLay networks and checkpoints: shapes of every variant, gradients through the
discriminator, safetensors round trips, the torchvision-compatible ImageNet loader."""
from __future__ import annotations

import json

import pytest
import torch

from racklay.checkpoint import load_checkpoint, load_model, save_checkpoint
from racklay.losses import lsgan_discriminator_loss, lsgan_generator_loss, one_hot_layouts
from racklay.model import (
    Discriminators,
    ModelConfig,
    RackLayNet,
    ResNet18Encoder,
    build_model,
    count_parameters,
    load_imagenet_weights,
)

IMG, LAY, R = 64, 32, 3


def _x(n=2, seed=0):
    return torch.randn(n, 3, IMG, IMG, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("decoder", ["light", "paper", "columns", "fast", "struct"])
@pytest.mark.parametrize("views", [("top",), ("front",), ("top", "front")])
@pytest.mark.parametrize("disc", [False, True])
def test_output_shapes_of_every_variant(decoder, views, disc):
    cfg = ModelConfig(R=R, image_size=IMG, layout_size=LAY, views=views, decoder=decoder, disc=disc)
    assert cfg.variant() == "RackLay-" + ("D" if len(views) == 2 else "S") + ("-disc" if disc else "")
    net = RackLayNet(cfg).eval()
    with torch.no_grad():
        out = net(_x())
    assert set(out) == set(views)
    for v in views:
        assert out[v].shape == (2, R, 3, LAY, LAY)
        assert torch.isfinite(out[v]).all()
    if disc:
        d = Discriminators(cfg)
        score = d(views[0], out[views[0]].softmax(2))
        assert score.shape == (2, 1, LAY // 16, LAY // 16)


def test_columns_decoder_grows_from_light_and_learns_per_column():
    """A light checkpoint grown into a columns model computes exactly what it did (the column
    map starts at zero); once the map is non-zero, what one image column holds changes the
    layout's matching columns far more than the opposite ones; an input of another height is
    refused with a message naming the built height."""
    from racklay.checkpoint import load_grown

    light = ModelConfig(R=2, image_size=(64, 128), layout_size=32, views=("top",), encoder="resnet18")
    cols = ModelConfig.from_dict({**light.to_dict(), "decoder": "columns"})
    a = RackLayNet(light).eval()
    b = RackLayNet(cols).eval()
    load_grown(b, a.state_dict(), "light", "light.safetensors")
    x = torch.randn(2, 3, 64, 128, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        assert torch.equal(a(x)["top"], b(x)["top"])
        torch.nn.init.normal_(b.decoders["top"].col_map.weight, std=0.05)
        y0 = b(x)["top"]
        x2 = x.clone()
        x2[..., :16] = torch.randn(2, 3, 64, 16, generator=torch.Generator().manual_seed(2))   # left image columns
        d = (b(x2)["top"] - y0).abs().mean((0, 1, 2, 3))           # change per layout column
    assert d[:8].mean() > 2 * d[-8:].mean()                    # 2.8-4.3 over init seeds 0-9
    with pytest.raises(ValueError, match="built for 4 rows"):
        b(torch.randn(1, 3, 96, 128))
    with pytest.raises(ValueError, match="no place in a columns model"):
        load_grown(b, {**a.state_dict(), "stray.weight": torch.zeros(1)}, "light", "light.safetensors")
    cut = {k: v for k, v in a.state_dict().items() if not k.startswith("decoders.top.final")}
    with pytest.raises(ValueError, match="lacks tensors.*decoders.top.final"):
        load_grown(b, cut, "light", "light.safetensors")


def test_struct_width_and_fuse_kernel_are_architecture_options(tmp_path):
    """A narrower struct decoder (`struct_width`) with a 1 x 1 fuse conv (`struct_fuse_k`) is built
    as configured, saved and loaded back as the same network (same outputs); a checkpoint written
    before the options existed loads with the shipped architecture (width 128, 3 x 3 fuse); the
    options need the struct decoder and the kernel is 1 or 3."""
    cfg = ModelConfig(R=2, image_size=(64, 128), layout_size=32, decoder="struct", struct_width=16, struct_fuse_k=1)
    torch.manual_seed(0)
    m = RackLayNet(cfg).eval()
    for dec in m.decoders.values():
        assert dec.fuse[0].kernel_size == (1, 1) and dec.fuse[0].out_channels == 16
        assert dec.pos_head.in_channels == 16
    path = save_checkpoint(tmp_path / "narrow.safetensors", m, cfg)
    m2, cfg2, _ = load_model(path)
    assert (cfg2.struct_width, cfg2.struct_fuse_k) == (16, 1)
    x = torch.randn(1, 3, 64, 128, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(m(x).values(), m2(x).values()))
    old = {k: v for k, v in cfg.to_dict().items() if k not in ("struct_width", "struct_fuse_k")}
    assert (ModelConfig.from_dict(old).struct_width, ModelConfig.from_dict(old).struct_fuse_k) == (128, 3)
    with pytest.raises(ValueError, match="struct_width needs the struct decoder"):
        ModelConfig(decoder="light", struct_width=32)
    with pytest.raises(ValueError, match="struct_fuse_k must be one of"):
        ModelConfig(decoder="struct", struct_fuse_k=5)


def test_struct_joint_reads_both_views_from_one_trunk(tmp_path):
    """`struct_joint`: the first view's decoder holds the one trunk (fuse conv, row attention, 1-D
    convs), the other view only its heads, each view placing its shelves itself; the model saves
    and loads back as the same network; it needs both views, and a checkpoint with separate
    trunks cannot initialise it (one error naming the option)."""
    from racklay.checkpoint import check_init, load_checkpoint
    from racklay.config import TrainConfig

    base = dict(R=2, image_size=(64, 128), layout_size=32, decoder="struct", struct_width=16, struct_gap=True)
    torch.manual_seed(0)
    m = RackLayNet(ModelConfig(**base, struct_joint=True)).eval()
    sep = RackLayNet(ModelConfig(**base)).eval()
    assert hasattr(m.decoders["top"], "fuse") and not hasattr(m.decoders["front"], "fuse")
    assert not hasattr(m.decoders["front"], "pos_seq") and hasattr(m.decoders["front"], "pos_head")
    assert m.trunk_decoder("front") is m.decoders["top"] and sep.trunk_decoder("front") is sep.decoders["front"]
    assert count_parameters(m) < count_parameters(sep)
    x = torch.randn(2, 3, 64, 128, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        out, st = m(x, with_structure=True)
    assert set(out) == {"top", "front"} and out["front"].shape == (2, 2, 3, 32, 32)
    assert not torch.equal(st["top"]["centre"], st["front"]["centre"])     # each view's own placement
    assert st["top"]["extent"].shape == st["front"]["extent"].shape == (2, 2)
    with pytest.raises(ValueError, match="no trunk of its own"):
        m.decoders["front"].structure(m.encoder(x))
    path = save_checkpoint(tmp_path / "joint.safetensors", m, m.cfg)
    m2, cfg2, _ = load_model(path)
    assert cfg2.struct_joint
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(m(x).values(), m2(x).values()))
    with pytest.raises(ValueError, match="struct_joint shares one trunk"):
        ModelConfig(**base, struct_joint=True, views=("front",))
    with pytest.raises(ValueError, match="struct_joint needs the struct decoder"):
        ModelConfig(decoder="light", struct_joint=True)
    sep_path = save_checkpoint(tmp_path / "sep.safetensors", sep, sep.cfg)
    run = TrainConfig(data="x", decoder="struct", struct_width=16, struct_gap=True, struct_joint=True, R=2,
                      image_size=(64, 128), layout_size=32)
    with pytest.raises(ValueError, match=r"sep.safetensors: cannot fine-tune.*struct_joint False \(run: True\)"):
        check_init(load_checkpoint(sep_path), run)


def test_struct_checkpoint_fine_tunes_at_another_layout_size(tmp_path):
    """A struct model's tensors do not depend on the layout size (its structure is drawn at any
    size), so `racklay train --init` accepts a struct checkpoint trained on 32² layouts for a run
    on 64² ones and loads every tensor; a dense decoder's checkpoint at another size is refused
    (one error naming the file and the size)."""
    from racklay.checkpoint import check_init, load_checkpoint, load_state_strict
    from racklay.config import TrainConfig

    base = dict(R=2, image_size=(64, 128), struct_width=16)
    torch.manual_seed(0)
    small = RackLayNet(ModelConfig(**base, layout_size=32, decoder="struct")).eval()
    path = save_checkpoint(tmp_path / "s32.safetensors", small, small.cfg)
    run = TrainConfig(data="x", decoder="struct", layout_size=64, **base)
    check_init(load_checkpoint(path), run)                      # no error
    big = RackLayNet(run.model_config()).eval()
    load_state_strict(big, load_checkpoint(path).section("model"), path, "model")
    x = torch.randn(1, 3, 64, 128, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        a, b = small.structures(small.features(x)), big.structures(big.features(x))
        assert big(x)["front"].shape[-1] == 64
    assert all(torch.equal(a[v][k], b[v][k]) for v in a for k in ("length", "extent", "box"))
    dense = RackLayNet(ModelConfig(R=2, image_size=(64, 128), layout_size=32, decoder="light")).eval()
    dpath = save_checkpoint(tmp_path / "d32.safetensors", dense, dense.cfg)
    with pytest.raises(ValueError, match=r"d32.safetensors: cannot fine-tune.*layout_size 32 \(run: 64\)"):
        check_init(load_checkpoint(dpath), TrainConfig(data="x", decoder="light", R=2, image_size=(64, 128),
                                                       layout_size=64))


def _struct_grown_with(field: str, **base_flags):
    """A small struct model (with `base_flags`), the same grown with `field` (a ModelConfig flag)
    from its weights (racklay.checkpoint.load_grown), both in eval mode, and an input batch."""
    from racklay.checkpoint import load_grown

    base = ModelConfig(R=2, image_size=(64, 128), layout_size=32, decoder="struct", **base_flags)
    torch.manual_seed(0)
    a = RackLayNet(base).eval()
    b = RackLayNet(ModelConfig.from_dict({**base.to_dict(), field: True})).eval()
    load_grown(b, a.state_dict(), "struct", "struct.safetensors")
    return a, b, torch.randn(2, 3, 64, 128, generator=torch.Generator().manual_seed(1))


def test_struct_detail_branch_grows_from_a_struct_checkpoint():
    """`struct_fine` (the 1/4 detail branch) grown from a struct checkpoint starts by predicting the
    same layouts (its last conv is zero; only the 1/8 sequence's upsampling differs) and the branch
    gets gradients from the per-position box scores. A fine checkpoint does not load into a model
    without the branch (the error says which flag), and the branch needs the struct decoder."""
    from racklay.checkpoint import load_grown

    a, b, x = _struct_grown_with("struct_fine")
    with torch.no_grad():
        (ya, sa), (yb, sb) = a(x, with_structure=True), b(x, with_structure=True)
        for v in ("top", "front"):
            assert torch.equal(ya[v].argmax(2), yb[v].argmax(2))
            assert torch.allclose(sa[v]["box"], sb[v]["box"], atol=0.05)
    # the zero-started branch learns: the per-position box scores reach its last conv
    b(x, with_structure=True)[1]["front"]["box"].square().sum().backward()
    assert b.decoders["front"].detail[-1].weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="no place in a struct model.*--struct-fine"):
        load_grown(a, b.state_dict(), "struct", "fine.safetensors")
    with pytest.raises(ValueError, match="struct_fine needs the struct decoder"):
        ModelConfig(decoder="light", struct_fine=True)


def test_struct_gap_output_grows_from_a_struct_checkpoint_and_cuts_box_runs():
    """`struct_gap` (the gap output) grown from a struct checkpoint starts by predicting the same
    layouts (its bias is -6: it cuts nothing a box logit below 6 calls a box); both views share one
    gap estimate; the drawn box logit is min(box, -gap), so a position with a positive gap logit
    has no box and a run of boxes is cut there; the output learns from its own scores; and it
    needs the struct decoder."""
    from racklay.checkpoint import load_grown
    from racklay.model import cut_at_gaps

    a, b, x = _struct_grown_with("struct_gap")
    with torch.no_grad():
        ya, (yb, sb) = a(x), b(x, with_structure=True)
    for v in ("top", "front"):
        assert torch.equal(ya[v], yb[v])
        assert torch.equal(sb[v]["box"], cut_at_gaps(sb[v]["box_raw"], sb[v]["gap"]))
    assert torch.equal(sb["top"]["gap"], sb["front"]["gap"])
    box = torch.full((1, 1, 6), 3.0)
    gap = torch.tensor([[[-6.0, -6.0, 5.0, -2.0, -6.0, -6.0]]])   # a gap at 2 only (logit > 0)
    assert (cut_at_gaps(box, gap) > 0).tolist() == [[[True, True, False, True, True, True]]]
    b.train()
    b(x, with_structure=True)[1]["front"]["gap"].square().sum().backward()
    assert b.decoders["front"].gap_head.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="no place in a struct model.*--struct-gap"):
        load_grown(a, b.state_dict(), "struct", "gap.safetensors")
    with pytest.raises(ValueError, match="struct_gap needs the struct decoder"):
        ModelConfig(decoder="light", struct_gap=True)


def test_struct_back_interval_grows_from_a_struct_checkpoint_and_draws_a_box_behind():
    """`struct_back` (a second depth interval in the top view) grown from a struct checkpoint starts
    by predicting the same layouts (its logit's bias is -6); the front view has none; once its logit
    says a box stands behind, the top view draws box over the back interval, and only there; it
    learns from the structure loss; it needs the struct decoder and a top view, and its checkpoint
    does not load into a model without it (the error names the flag)."""
    from racklay.checkpoint import load_grown
    from racklay.layout import BOX
    from racklay.structure import structure_loss

    a, b, x = _struct_grown_with("struct_back")
    with torch.no_grad():
        ya, (yb, sb) = a(x), b(x, with_structure=True)
    for v in ("top", "front"):
        assert torch.equal(ya[v].argmax(2), yb[v].argmax(2))
        assert torch.allclose(ya[v].exp(), yb[v].exp(), atol=0.01)           # probabilities within 1 %
    assert "back" in sb["top"] and "back" not in sb["front"]
    dec = b.decoders["top"]
    with torch.no_grad():
        dec.pos_head.bias[0] = 8.0                                     # a box at every position ...
        dec.back_head.bias.copy_(torch.tensor([8.0, 0.0, 4.0]))        # ... and one behind it, to the back edge
        st = b(x, with_structure=True)[1]["top"]
        top = b(x)["top"].argmax(2)
        dec.back_head.bias[0] = -8.0
        top_none = b(x)["top"].argmax(2)
    added = (top == BOX) & (top_none != BOX)
    assert added.any() and not ((top_none == BOX) & (top != BOX)).any()
    assert (st["back_far"] > st["back_near"]).all()
    b.train()
    truth = torch.zeros(2, 2, 32, 32, dtype=torch.long)
    truth[:, 0, 13:19, 6:26] = 1                                       # a shelf 6 px deep
    truth[:, 0, 13:14, 8:20] = 2                                       # a back box ...
    truth[:, 0, 16:19, 8:20] = 2                                       # ... behind a front box
    structure_loss("top", b.decoders["top"].structure(b.features(x)), truth, b.cfg.extent).backward()
    assert dec.back_head.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="no place in a struct model.*--struct-back"):
        load_grown(a, b.state_dict(), "struct", "back.safetensors")
    with pytest.raises(ValueError, match="struct_back needs the struct decoder"):
        ModelConfig(decoder="light", struct_back=True)
    with pytest.raises(ValueError, match="struct_back is a second depth interval of the top view"):
        ModelConfig(decoder="struct", struct_back=True, views=("front",))


def test_struct_brightness_cue_grows_from_a_struct_checkpoint_and_reads_dark_slots():
    """`struct_cue` (the brightness cue, a second gap detector) grown from a struct checkpoint with
    a gap output predicts exactly what the checkpoint did (its evidence starts at zero); the drawn
    gap logit is the features' plus the cue's logit less its bias, and the structure loss trains
    each detector by its own BCE (the cue learns from the true gaps, not from the sum); the
    decoders read the input's luminance (1 for a white photo); along a shelf the cue is darkest,
    and its local contrast lowest, where the photo's profile has a dark slot, and it flags the
    positions of a shelf placed partly outside the frame; it needs the struct decoder, the gap
    output and its own trunk."""
    from racklay.checkpoint import load_grown
    from racklay.structure import structure_loss
    from racklay.torchdata import IMAGENET_MEAN, IMAGENET_STD

    a, b, x = _struct_grown_with("struct_cue", struct_gap=True)
    with torch.no_grad():
        ya, yb = a(x), b(x)
    for v in ("top", "front"):
        assert torch.equal(ya[v], yb[v])
    b.train()
    st = b.decoders["front"].structure(b.features(x))
    head = b.decoders["front"].cue[-1]
    assert torch.allclose(st["gap"], st["gap_main"] + st["gap_cue"] - head.bias)
    truth = torch.zeros(2, 2, 32, 32, dtype=torch.long)
    truth[:, 0, 12:16, 4:12] = 2                                    # two boxes on shelf 0, a gap between them
    truth[:, 0, 12:16, 14:26] = 2
    truth[:, 0, 16, 2:28] = 1
    structure_loss("front", st, truth, b.cfg.extent).backward()
    assert head.weight.grad.abs().sum() > 0 and head.bias.grad.abs().sum() > 0
    assert b.decoders["front"].gap_head.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="no place in a struct model.*--struct-cue"):
        load_grown(a, b.state_dict(), "struct", "cue.safetensors")
    white = ((1 - torch.tensor(IMAGENET_MEAN)) / torch.tensor(IMAGENET_STD)).view(1, 3, 1, 1).expand(1, 3, 64, 128)
    lum = b.features(white)[-1]
    assert lum.shape == (1, 1, 32, 64) and torch.allclose(lum, torch.ones_like(lum), atol=1e-4)

    dec = b.decoders["front"]
    prof = torch.full((1, 2, 64), 0.8)
    prof[..., 40:43] = 0.2                                           # a dark slot at 0.63-0.67 of the width
    shelf = torch.zeros(1, 2, 6)
    shelf[0, 1, 3] = 0.5                                             # shelf 1 centred on the right edge
    cue = dec.cue_features({"lum": prof}, shelf, torch.full((1, 2), 0.5)).reshape(2, dec.N_CUE, dec.T)
    T = dec.T
    slot = int(0.65 * T)
    assert abs(int(cue[0, 0].argmax()) - slot) <= 1 and abs(int(cue[0, 1].argmin()) - slot) <= 1
    assert cue[0, 0, slot] > 0.5 and abs(float(cue[0, 0, : T // 2].mean())) < 0.2
    assert cue[0, 2].eq(1).all() and cue[1, 2, : T // 2].eq(1).all() and cue[1, 2, T // 2 + 1:].eq(0).all()
    with pytest.raises(ValueError, match="struct_cue needs the struct decoder"):
        ModelConfig(decoder="light", struct_cue=True)
    with pytest.raises(ValueError, match="struct_cue is a second gap detector: it needs the gap output"):
        ModelConfig(decoder="struct", struct_cue=True)
    with pytest.raises(ValueError, match="struct_cue is not built for struct_joint"):
        ModelConfig(decoder="struct", struct_cue=True, struct_gap=True, struct_joint=True)


def test_the_gap_cut_can_be_switched_off_to_draw_the_box_output_alone():
    """`set_gap_cut(False)` draws boxes from the (view-tied) box output without the gap output's
    cuts, in both views, and leaves every other output as it was; on again restores the trained
    drawing; a model without a gap output says so."""
    _, b, x = _struct_grown_with("struct_gap")
    with torch.no_grad():
        for dec in b.decoders.values():
            dec.gap_head.bias.fill_(4.0)                     # a gap everywhere: every box cut
        cut, sc = b(x, with_structure=True)
        b.set_gap_cut(False)
        raw, sr = b(x, with_structure=True)
        b.set_gap_cut(True)
        again = b(x)
    for v in ("top", "front"):
        assert torch.equal(sr[v]["box"], sr[v]["box_raw"]) and torch.equal(sr[v]["box_raw"], sc[v]["box_raw"])
        assert (sc[v]["box"] <= -4.0 + 1e-4).all() and not torch.equal(sc[v]["box"], sr[v]["box"])
        assert torch.equal(sr[v]["length"], sc[v]["length"]) and torch.equal(again[v], cut[v])
    with pytest.raises(ValueError, match="no gap output"):
        RackLayNet(ModelConfig(R=2, image_size=(64, 128), layout_size=96, encoder="resnet18")).set_gap_cut(False)
    from racklay.predict import Predictor
    with pytest.raises(ValueError, match="torch backend; an ONNX graph has the cut built in"):
        Predictor("model.onnx", cut_gaps=False)


def test_fast_decoder_is_light_with_its_last_conv_before_the_resize():
    """`fast` has exactly `light`'s tensors (a light checkpoint loads into it strictly, both ways),
    computes the logits at the last stage's resolution and only then resizes them to S, so it
    matches light's layouts closely (same weights, different order of conv and resize) at a
    fraction of the full-resolution work; the train CLI offers every decoder the model has."""
    from racklay.checkpoint import load_grown
    from racklay.cli import build_parser
    from racklay.model import DECODERS, SAME_TENSOR_DECODERS

    light = ModelConfig(R=2, image_size=(64, 128), layout_size=96, views=("top",), encoder="resnet18")
    fast = ModelConfig.from_dict({**light.to_dict(), "decoder": "fast"})
    a = RackLayNet(light).eval()
    b = RackLayNet(fast).eval()
    assert ("light", "fast") in SAME_TENSOR_DECODERS and set(a.state_dict()) == set(b.state_dict())
    load_grown(b, a.state_dict(), "light", "light.safetensors")
    seen = {}
    b.decoders["top"].head.register_forward_hook(lambda m, i, o: seen.update(head=o.shape))
    x = torch.randn(2, 3, 64, 128, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        ya, yb = a(x)["top"], b(x)["top"]
    assert seen["head"][-2:] == (32, 64)                      # 1/2 of the input, not 96 x 96
    assert yb.shape == ya.shape == (2, 2, 3, 96, 96)
    assert not torch.equal(ya, yb)
    assert torch.corrcoef(torch.stack([ya.flatten(), yb.flatten()]))[0, 1] > 0.9
    parser = build_parser()
    assert [parser.parse_args(["train", "--decoder", d]).decoder for d in DECODERS] == list(DECODERS)


def test_layout_size_independent_of_image_size():
    for decoder in ("light", "paper"):
        net = RackLayNet(ModelConfig(R=2, image_size=96, layout_size=40, decoder=decoder)).eval()
        with torch.no_grad():
            out = net(torch.randn(1, 3, 96, 96))
        assert out["front"].shape == (1, 2, 3, 40, 40)


def test_paper_decoder_over_resolves_then_pools():
    """The authors' decoder works at 2·S before its max-pool; the light one never exceeds S."""
    net = RackLayNet(ModelConfig(R=2, image_size=IMG, layout_size=LAY, views=("top",), decoder="paper")).eval()
    seen = []
    net.decoders["top"].pool.register_forward_hook(lambda m, i, o: seen.append((i[0].shape[-1], o.shape[-1])))
    with torch.no_grad():
        net(_x(1))
    assert seen == [(2 * LAY, LAY)]
    light = RackLayNet(ModelConfig(R=2, image_size=IMG, layout_size=LAY, views=("top",))).eval()
    sizes = []
    for m in light.decoders["top"].modules():
        if isinstance(m, torch.nn.Conv2d):
            m.register_forward_hook(lambda m, i, o: sizes.append(o.shape[-1]))
    with torch.no_grad():
        light(_x(1))
    assert max(sizes) == LAY


@pytest.mark.parametrize("decoder", ["light", "paper"])
def test_discriminator_gradient_reaches_decoder(decoder):
    cfg = ModelConfig(R=2, image_size=IMG, layout_size=LAY, decoder=decoder, disc=True)
    net, disc = RackLayNet(cfg), Discriminators(cfg)
    out = net(_x(1))
    adv = sum(lsgan_generator_loss(disc(v, out[v].softmax(2))) for v in out)
    adv.backward()
    for v in cfg.views:
        g = net.decoders[v].head.weight.grad
        assert g is not None and g.abs().sum() > 0, f"no adversarial gradient on the {v} decoder"
    stem = next(net.encoder.parameters())     # the first convolution of the encoder
    assert stem.grad is not None and stem.grad.abs().sum() > 0
    # the discriminator's own loss separates real one-hot layouts from predictions
    target = torch.randint(0, 3, (1, 2, LAY, LAY))
    dl = lsgan_discriminator_loss(disc("top", one_hot_layouts(target)), disc("top", out["top"].softmax(2).detach()))
    assert dl.item() > 0
    assert one_hot_layouts(target).sum(2).eq(1).all()


def test_model_config_validation():
    with pytest.raises(ValueError, match="views"):
        ModelConfig(views=("side",))
    with pytest.raises(ValueError, match="decoder"):
        ModelConfig(decoder="huge")
    with pytest.raises(ValueError, match="multiple of 32"):
        ModelConfig(image_size=100)
    assert ModelConfig.from_dict(ModelConfig(R=2).to_dict()) == ModelConfig(R=2)
    wide = ModelConfig(image_size=(64, 96), views=("front",))
    assert json.loads(json.dumps(wide.to_dict())) == wide.to_dict()   # JSON-able as it is
    assert ModelConfig.from_dict(json.loads(json.dumps(wide.to_dict()))) == wide
    # a dict field (racklay calibrate's decision_bias) round-trips through JSON too
    cal = ModelConfig(decision_bias={"top": (0.0, 0.5, 1.25)})
    assert ModelConfig.from_dict(json.loads(json.dumps(cal.to_dict()))) == cal
    with pytest.raises(ValueError, match="unknown model config keys: \\['nope'\\]"):
        ModelConfig.from_dict({**wide.to_dict(), "nope": 1})
    # a config written before the encoder was a choice (older checkpoints) is a ResNet-18 one
    old = {k: v for k, v in ModelConfig(R=2, encoder="resnet18").to_dict().items() if k not in ("encoder", "letterbox")}
    assert ModelConfig.from_dict(old).encoder == "resnet18"


@pytest.mark.slow
def test_checkpoint_round_trip_is_exact(tmp_path):
    cfg = ModelConfig(R=2, image_size=IMG, layout_size=LAY, decoder="paper", disc=True)
    net, disc = RackLayNet(cfg), Discriminators(cfg)
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    net.train()
    loss = sum(o.square().mean() for o in net(_x()).values())
    loss.backward()
    opt.step()                                    # optimiser state + BN running stats change
    path = save_checkpoint(tmp_path / "m.safetensors", net, cfg, optimizer={"gen": opt},
                           extra={"epoch": 3, "note": "x"}, disc=disc)
    net.eval()
    model, cfg2, meta = load_model(path)
    assert cfg2 == cfg and meta == {"epoch": 3, "note": "x"}
    assert not model.training
    x = _x(seed=1)
    with torch.no_grad():
        a, b = net(x), model(x)
    for v in a:
        assert torch.equal(a[v], b[v])
    ck = load_checkpoint(path)
    opt2 = torch.optim.Adam(model.parameters(), 1e-3)
    ck.load_optimizer(opt2, "gen")
    s1, s2 = opt.state_dict()["state"], opt2.state_dict()["state"]
    assert s1.keys() == s2.keys()
    assert all(torch.equal(s1[k]["exp_avg_sq"], s2[k]["exp_avg_sq"]) for k in s1)
    d2 = Discriminators(cfg)
    ck.load_discriminators(d2)
    assert all(torch.equal(p, q) for p, q in zip(disc.state_dict().values(), d2.state_dict().values()))


def test_load_model_rejects_bad_files(tmp_path):
    from safetensors.torch import save_file

    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"\x00\x01not a checkpoint" * 10)
    with pytest.raises(ValueError, match="junk.safetensors"):
        load_model(junk)
    foreign = tmp_path / "foreign.safetensors"
    save_file({"w": torch.zeros(2)}, str(foreign))
    with pytest.raises(ValueError, match="foreign.safetensors.*metadata"):
        load_model(foreign)
    with pytest.raises(FileNotFoundError, match="missing.safetensors"):
        load_model(tmp_path / "missing.safetensors")
    # right format, wrong shapes for the recorded config
    cfg = ModelConfig(R=2, image_size=IMG, layout_size=LAY)
    p = save_checkpoint(tmp_path / "r2.safetensors", RackLayNet(cfg), ModelConfig(R=3, image_size=IMG, layout_size=LAY))
    with pytest.raises(ValueError, match="r2.safetensors.*do not match"):
        load_model(p)


def test_checkpoint_bytes_changed_after_writing_are_refused(tmp_path):
    """A checkpoint carries a SHA-256 of its header and tensors: one flipped bit in a weight (which
    silently changed predictions before) or an edited header value is refused with one line; a
    file written before the hash existed still loads."""
    import json
    import struct

    from safetensors.torch import save

    from racklay.checkpoint import HASH_KEY, content_hash

    cfg = ModelConfig(R=2, image_size=IMG, layout_size=LAY)
    torch.manual_seed(0)
    good = save_checkpoint(tmp_path / "good.safetensors", RackLayNet(cfg), cfg, extra={"epoch": 3})
    raw = good.read_bytes()
    n = struct.unpack("<Q", raw[:8])[0]
    flipped = bytearray(raw)
    flipped[8 + n + (len(raw) - 8 - n) // 2] ^= 0x10          # one bit in the middle of the weights
    bad = tmp_path / "flipped.safetensors"
    bad.write_bytes(bytes(flipped))
    with pytest.raises(ValueError, match=r"flipped\.safetensors: checkpoint content does not match its "
                                         r"recorded SHA-256"):
        load_model(bad)
    edited = tmp_path / "edited.safetensors"
    edited.write_bytes(raw.replace(b'\\"epoch\\": 3', b'\\"epoch\\": 4'))
    assert edited.read_bytes() != raw
    with pytest.raises(ValueError, match="edited.safetensors: checkpoint content does not match"):
        load_checkpoint(edited)
    # a checkpoint from before the hash: same tensors and header, no hash key -> loads unchecked
    ck = load_checkpoint(good)
    header = json.dumps({"format": "racklay-checkpoint", "version": 1, "config": cfg.to_dict(),
                         "meta": {"epoch": 3}, "optim": {}})
    old = tmp_path / "old.safetensors"
    old.write_bytes(save(ck.tensors, metadata={"racklay": header}))
    assert load_model(old)[2] == {"epoch": 3}
    assert HASH_KEY not in (load_checkpoint(old).meta or {})
    # the hash covers every dtype a model may hold (bf16 has no numpy twin)
    assert content_hash("h", {"a": torch.ones(3, dtype=torch.bfloat16)}) != content_hash(
        "h", {"a": torch.ones(3, dtype=torch.float16)})


def _fake_torchvision_state(seed=0):
    torch.manual_seed(seed)
    sd = {k: torch.randn_like(v.float()).to(v.dtype) if v.dtype.is_floating_point else v
          for k, v in ResNet18Encoder().state_dict().items()}
    sd["fc.weight"] = torch.randn(1000, 512)
    sd["fc.bias"] = torch.randn(1000)
    return sd


@pytest.mark.parametrize("fmt", ["pth", "safetensors"])
def test_imagenet_loader_accepts_torchvision_names(tmp_path, fmt):
    sd = _fake_torchvision_state()
    # torchvision's names, spelled out: a renamed encoder would fail here
    for k in ("conv1.weight", "bn1.running_mean", "layer1.0.conv1.weight", "layer2.0.downsample.0.weight",
              "layer4.1.bn2.weight", "layer3.0.downsample.1.num_batches_tracked"):
        assert k in sd
    path = tmp_path / f"resnet18.{fmt}"
    if fmt == "pth":
        torch.save(sd, path)
    else:
        from safetensors.torch import save_file
        save_file(sd, str(path))
    net = build_model(ModelConfig(R=2, image_size=IMG, layout_size=LAY, encoder="resnet18"), imagenet_weights=path)
    assert torch.equal(net.encoder.layer3[1].conv2.weight, sd["layer3.1.conv2.weight"])
    assert torch.equal(net.encoder.bn1.running_var, sd["bn1.running_var"])


def test_imagenet_loader_rejects_wrong_files(tmp_path):
    enc = ResNet18Encoder()
    text = tmp_path / "notes.pth"
    text.write_text("hello")
    with pytest.raises(ValueError, match="notes.pth"):
        load_imagenet_weights(enc, text)
    sd = _fake_torchvision_state()
    del sd["layer2.1.conv1.weight"]
    missing = tmp_path / "partial.pth"
    torch.save(sd, missing)
    with pytest.raises(ValueError, match="partial.pth.*missing.*layer2.1.conv1.weight"):
        load_imagenet_weights(enc, missing)
    sd = _fake_torchvision_state()
    sd["conv1.weight"] = torch.randn(64, 3, 3, 3)
    shaped = tmp_path / "resnet34ish.pth"
    torch.save(sd, shaped)
    with pytest.raises(ValueError, match="resnet34ish.pth.*shape"):
        load_imagenet_weights(enc, shaped)
    a_list = tmp_path / "list.pth"
    torch.save([1, 2], a_list)
    with pytest.raises(ValueError, match="list.pth.*state dict"):
        load_imagenet_weights(enc, a_list)


@pytest.mark.parametrize("decoder", ["struct", "light"])
def test_flip_averaging_predicts_a_mirror_image_as_the_mirror_of_the_prediction(decoder):
    """`set_flip_average(True)` averages each image's prediction with its mirror image's: the
    result is exactly mirror-symmetric (the mirrored photo gives the mirrored layouts, x -> -x),
    which neither prediction alone is; a struct model still draws rectangles from averaged
    structures (the flip-averaged structure's per-position fields of a mirrored photo are the
    reversed ones), and off again gives the plain prediction back."""
    cfg = ModelConfig(R=2, image_size=(64, 128), layout_size=LAY, decoder=decoder, encoder="resnet18",
                      struct_gap=decoder == "struct")
    net = RackLayNet(cfg).eval()
    torch.manual_seed(1)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))           # break the init's near-symmetry
    x = torch.randn(2, 3, 64, 128, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        plain, mirrored = net(x), net(x.flip(-1))
        assert any((plain[v] - mirrored[v].flip(-1)).abs().max() > 1e-3 for v in plain)
        net.set_flip_average(True)
        if decoder == "struct":
            (a, sa), (b, sb) = net(x, with_structure=True), net(x.flip(-1), with_structure=True)
            for v in ("top", "front"):
                assert torch.allclose(sa[v]["box"], sb[v]["box"].flip(-1), atol=1e-5)
                assert torch.allclose(sa[v]["length"], sb[v]["length"], rtol=1e-5)
                # the shelf's placement in the mirror image is mirrored: centre x -> -x, same half-width
                assert torch.allclose(sa[v]["centre"], -sb[v]["centre"], atol=1e-5)
                assert torch.allclose(sa[v]["half"], sb[v]["half"], rtol=1e-5)
        else:
            a, b = net(x), net(x.flip(-1))
        for v in ("top", "front"):
            assert a[v].shape == plain[v].shape
            assert torch.allclose(a[v], b[v].flip(-1), atol=1e-4)
            assert torch.allclose(a[v].exp().sum(2), torch.ones(()), atol=1e-4)   # log-probabilities
        net.set_flip_average(False)
        assert all(torch.equal(net(x)[v], plain[v]) for v in plain)
    from racklay.predict import Predictor
    with pytest.raises(ValueError, match="flip averaging is for the torch backend"):
        Predictor("model.onnx", flip_average=True)


@pytest.mark.parametrize("encoder,decoder", [("efficientnet-lite0", "struct"), ("resnet18", "paper"),
                                             ("resnet18", "light"), ("resnet18", "fast"), ("resnet18", "columns")])
def test_folding_batch_norms_keeps_the_prediction_and_leaves_no_norm(encoder, decoder, tmp_path):
    """`fold_batchnorm` (what `racklay predict` runs) folds every batch norm of every encoder and
    decoder into the convolution before it: no norm left, the same layouts (norms with
    non-trivial statistics, so a missed or wrong fold shows), and it refuses a model in training."""
    from racklay.model import fold_batchnorm
    from racklay.predict import Predictor

    cfg = ModelConfig(R=2, image_size=(64, 128), layout_size=LAY, decoder=decoder, encoder=encoder,
                      struct_fine=decoder == "struct", struct_gap=decoder == "struct")
    net = RackLayNet(cfg)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)):
                m.running_mean.copy_(0.3 * torch.randn(m.num_features, generator=g))
                m.running_var.copy_(0.5 + torch.rand(m.num_features, generator=g))
                m.weight.copy_(1 + 0.3 * torch.randn(m.num_features, generator=g))
                m.bias.copy_(0.2 * torch.randn(m.num_features, generator=g))
    n_norms = sum(isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)) for m in net.modules())
    with pytest.raises(ValueError, match="eval mode"):
        fold_batchnorm(net)
    net.eval()
    save_checkpoint(tmp_path / "m.safetensors", net, cfg)
    x = torch.randn(2, 3, 64, 128, generator=g)
    with torch.no_grad():
        before = net(x)
        assert fold_batchnorm(net) == n_norms > 0
        after = net(x)
    assert not any(isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)) for m in net.modules())
    for v in before:        # float rounding only: random nets' logits reach ~100
        assert (before[v] - after[v]).abs().max() <= 1e-5 * before[v].abs().max(), v
        assert (before[v].argmax(2) == after[v].argmax(2)).float().mean() > 0.999, v
    pred = Predictor(tmp_path / "m.safetensors")
    assert not any(isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)) for m in pred.model.modules())


def test_position_columns_span_the_placed_shelf():
    """`position_columns`: a shelf centred in the image with half-width 0.5 reads its T positions
    at their centres from the left edge to the right edge; moving the centre shifts every column."""
    from racklay.model import position_columns

    cols = position_columns(torch.tensor([0.0, 0.25]), torch.tensor([0.5, 0.5]), 4)
    assert torch.allclose(cols[0], torch.tensor([0.125, 0.375, 0.625, 0.875]))
    assert torch.allclose(cols[1], cols[0] + 0.25)
