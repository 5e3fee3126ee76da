"""The structured form of layouts (racklay.structure), the `struct` decoder built on it, and the
known-dimension scale (racklay.layout.length_factors / scale_about_origin, `--shelf-length`,
`racklay eval --scale-from-truth`)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from conftest import make_toy
from racklay import layout as L
from racklay.cli import main as racklay_main
from racklay.model import ModelConfig, RackLayNet
from racklay.structure import DEFAULT_TAU_PX, HARD_TAU_PX, rasterize, structure_loss, truth_structure

S, EXT = 128, 8.0
G = L.Grid(S, EXT)


def _two_box_shelf(length=2.0, depth=0.8, clear=0.5):
    """A shelf with two separate boxes (a gap between them) and an empty one above it."""
    boxes = [L.Box(-0.45 * length / 2, -0.05, 0.3, 0.5, 0.3), L.Box(0.5 * length / 2, 0.1, 0.35, 0.4, 0.45)]
    lay = L.rasterize_shelf(L.Shelf(length, depth, clear), boxes, G)
    return L.stack_shelves([lay, L.rasterize_shelf(L.Shelf(length, depth, clear), [], G)], R=3, grid=G)


def _runs(row: np.ndarray) -> int:
    """Number of separate runs of True along a 1-D array."""
    return int(np.count_nonzero(np.diff(np.concatenate([[0], row.astype(np.int8), [0]])) > 0))


def _as_prediction(tr: dict) -> dict:
    """A ground-truth structure as a confident prediction (bool fields -> +-20 logits)."""
    return {k: (v.float() * 40 - 20 if v.dtype == torch.bool else v.float()) for k, v in tr.items()}


@pytest.mark.parametrize("view", ["front", "top"])
def test_structure_of_a_layout_draws_it_back_with_its_separate_boxes(view):
    """truth_structure -> rasterize reproduces layouts of axis-aligned boxes standing on their board:
    two boxes with a gap stay two boxes, the empty shelf stays empty, the missing channel stays."""
    top, front = _two_box_shelf()
    lay = torch.from_numpy(top if view == "top" else front)[None].long()
    tr = truth_structure(view, lay, EXT, T=S)
    assert tr["presence"].tolist() == [[True, True, False]]
    assert tr["length"][0, 0].item() == pytest.approx(2.0, abs=G.res)
    drawn = rasterize(view, _as_prediction(tr), S, EXT, tau_px=0.01).argmax(2)[0].numpy()
    truth = lay[0].numpy()
    assert (drawn == truth).mean() > 0.998
    assert _runs((drawn[0] == L.BOX).any(0)) == 2
    assert not (drawn[1] == L.BOX).any() and not drawn[2].any()


def _front_and_back_boxes(length=2.0, depth=0.8, clear=0.5):
    """Top view of a shelf with a box behind another over part of its length (a gap in depth
    between them), and a single box beside them."""
    boxes = [L.Box(-0.45, -0.25, 0.9, 0.25, 0.3), L.Box(-0.45, 0.25, 0.9, 0.2, 0.4), L.Box(0.5, -0.2, 0.6, 0.35, 0.3)]
    shelf = L.Shelf(length, depth, clear)
    top, _ = L.stack_shelves([L.rasterize_shelf(shelf, boxes, G), L.rasterize_shelf(shelf, [], G)], R=2, grid=G)
    return torch.from_numpy(top)[None].long()


def test_a_back_interval_draws_a_box_behind_another_and_one_interval_cannot():
    """Top view, a box behind the front one in the same columns: with the back interval
    (`truth_structure(back=True)`, the struct_back form) the structure draws both boxes and the
    free board between them; with one interval per position the two merge into one span (the
    board between them drawn as box). The single box beside them has nothing behind it."""
    lay = _front_and_back_boxes()
    truth = lay[0, 0].numpy()
    gap_cols = (truth == L.BOX).any(0) & ((np.diff((truth == L.BOX).astype(np.int8), axis=0) > 0).sum(0) == 2)
    assert gap_cols.sum() > 10                                     # the layout has columns with two boxes in depth
    hull = rasterize("top", _as_prediction(truth_structure("top", lay, EXT, T=S)), S, EXT, tau_px=0.01)
    back_tr = truth_structure("top", lay, EXT, T=S, back=True)
    both = rasterize("top", _as_prediction(back_tr), S, EXT, tau_px=0.01)
    hull, both = hull.argmax(2)[0, 0].numpy(), both.argmax(2)[0, 0].numpy()
    assert (both == truth).mean() > 0.998
    assert ((both[:, gap_cols] == L.BOX) == (truth[:, gap_cols] == L.BOX)).mean() > 0.99
    assert (hull[:, gap_cols] == L.BOX).sum() > (truth[:, gap_cols] == L.BOX).sum() + 2 * gap_cols.sum()
    assert back_tr["back"][0, 0].any() and not back_tr["back"][0, 1].any()      # the empty shelf: nothing behind
    assert (back_tr["box"][0, 0] & ~back_tr["back"][0, 0]).any()                   # the single box: nothing behind
    single = truth_structure("top", lay, EXT, T=S)                 # near/far of a column with one box: the same
    one = back_tr["box"][0, 0] & ~back_tr["back"][0, 0]
    for k in ("near", "far"):
        assert torch.allclose(back_tr[k][0, 0][one], single[k][0, 0][one])
    good = structure_loss("top", _as_prediction(back_tr), lay, EXT)
    wrong = _as_prediction(back_tr)
    wrong["back"] = -wrong["back"]
    assert good < 1e-3 and structure_loss("top", wrong, lay, EXT) > good + 1.0


@pytest.mark.parametrize("view", ["front", "top", "top-back"])
@pytest.mark.parametrize("tau", [DEFAULT_TAU_PX, HARD_TAU_PX])
def test_rasterize_draws_the_same_layouts_in_its_window_as_on_the_whole_grid(view, tau):
    """Drawing only the window the shelves can reach (the default, for speed) gives the whole
    grid's log-probabilities and argmax, for shelves of different sizes in one batch, and with the
    training edge softness the same gradients (the prediction softness has next to none)."""
    g = torch.Generator().manual_seed(3)
    N, R, T = 2, 3, 24
    st = {"presence": torch.randn(N, R, generator=g), "length": torch.rand(N, R, generator=g) * 3 + 0.3,
          "extent": torch.rand(N, R, generator=g) + 0.2, "box": torch.randn(N, R, T, generator=g) * 3}
    if view == "front":
        st["height"] = torch.rand(N, R, T, generator=g)
    else:
        st["near"], st["far"] = torch.rand(N, R, T, generator=g) * 0.5, 0.5 + torch.rand(N, R, T, generator=g) * 0.5
    if view == "top-back":
        st["back"] = torch.randn(N, R, T, generator=g) * 3
        st["back_near"] = 0.5 + torch.rand(N, R, T, generator=g) * 0.3
        st["back_far"] = st["back_near"] + torch.rand(N, R, T, generator=g) * (1 - st["back_near"])
    view = view.removesuffix("-back")
    drawn, grads = [], []
    for window in (True, False):
        leaves = {k: v.clone().requires_grad_() for k, v in st.items()}
        y = rasterize(view, leaves, S, EXT, tau, window=window)
        drawn.append(y.detach())
        grads.append(torch.autograd.grad(y[:, :, 1:].exp().sum() + y[:, :, 0].sum(), list(leaves.values())))
    assert torch.allclose(drawn[0], drawn[1], atol=1e-5)
    assert torch.equal(drawn[0].argmax(2), drawn[1].argmax(2))
    if tau == DEFAULT_TAU_PX:
        for a, b in zip(*grads):
            assert torch.allclose(a, b, rtol=1e-3, atol=1e-3 * b.abs().max().item())


def test_structure_loss_is_small_for_the_truth_and_large_for_a_wrong_scale():
    top, front = _two_box_shelf()
    for view, arr in (("top", top), ("front", front)):
        lay = torch.from_numpy(arr)[None].long()
        tr = truth_structure(view, lay, EXT)
        good = structure_loss(view, _as_prediction(tr), lay, EXT)
        wrong = _as_prediction(tr)
        wrong["length"] = wrong["length"] * 2
        assert good < 1e-3
        assert structure_loss(view, wrong, lay, EXT) > good + 0.5


def test_placement_loss_pulls_each_labelled_shelf_to_its_span_in_the_image():
    """Placement supervision: L1 of the centre and the log half-width against each shelf's
    labelled span, only on shelves that exist and have a span (a render without one, NaN, and an
    absent shelf cost nothing and get no gradient); `placement_weight` scales it inside
    `structure_loss`, 0 leaves the loss as it was; a structure without a placement is refused."""
    import math

    from racklay.structure import placement_loss

    _, front = _two_box_shelf()
    lay = torch.from_numpy(front)[None].long()                     # shelves 0 and 1 present, 2 absent
    st = _as_prediction(truth_structure("front", lay, EXT))
    centre = torch.tensor([[0.1, 0.3, -0.2]], requires_grad=True)
    st["centre"], st["half"] = centre, torch.tensor([[0.4, 0.4, 0.4]])
    nan = float("nan")
    spans = torch.tensor([[[0.2, 0.8], [nan, nan], [0.0, 1.0]]])   # shelf 0 centred, half-width 0.3
    want = 0.1 + abs(math.log(0.4) - math.log(0.3))
    assert placement_loss(st, spans, torch.tensor([[True, True, False]])).item() == pytest.approx(want, rel=1e-5)
    assert placement_loss(st, spans, torch.tensor([[False, True, False]])) is None   # no present shelf has a span
    base = structure_loss("front", st, lay, EXT, spans=spans)                     # weight 0: unchanged
    assert base.item() == pytest.approx(structure_loss("front", st, lay, EXT).item())
    with_it = structure_loss("front", st, lay, EXT, spans=spans, placement_weight=2.0)
    assert (with_it - base).item() == pytest.approx(2 * want, rel=1e-4)
    with_it.backward()
    assert centre.grad[0, 0] > 0 and centre.grad[0, 1] == 0 and centre.grad[0, 2] == 0
    del st["centre"]
    with pytest.raises(ValueError, match="placement"):
        structure_loss("front", st, lay, EXT, spans=spans, placement_weight=1.0)


def test_gap_weight_makes_bridging_two_boxes_cost_more():
    """The gaps between boxes are the empty positions with a box on either side; with
    `gap_weight` > 1 a prediction that bridges two boxes (one box run) costs more than with the
    default weight, a prediction that keeps the gap costs the same."""
    from racklay.structure import gap_positions

    box = torch.tensor([[0, 1, 1, 0, 0, 1, 0, 0]], dtype=torch.bool)
    assert gap_positions(box).tolist() == [[False, False, False, True, True, False, False, False]]
    _, front = _two_box_shelf()
    lay = torch.from_numpy(front)[None].long()
    tr = truth_structure("front", lay, EXT)
    good = _as_prediction(tr)
    bridged = _as_prediction(tr)
    bridged["box"] = torch.where(gap_positions(tr["box"]), torch.tensor(20.0), bridged["box"])
    assert gap_positions(tr["box"]).any()
    for w in (1.0, 10.0):
        assert structure_loss("front", good, lay, EXT, gap_weight=w) < 1e-3
    assert (structure_loss("front", bridged, lay, EXT, gap_weight=10.0)
            > 5 * structure_loss("front", bridged, lay, EXT, gap_weight=1.0))


def test_a_gap_output_is_trained_on_the_gaps_and_its_cut_costs_the_box_loss_nothing():
    """With a gap output (StructDecoder(gap=True)) the loss has a term of its own on the gap logit at
    the gaps between boxes; the box loss is taken before the cut, so a gap output that cuts where
    the truth has a gap does not change it."""
    from racklay.model import cut_at_gaps
    from racklay.structure import gap_positions

    _, front = _two_box_shelf()
    lay = torch.from_numpy(front)[None].long()
    tr = truth_structure("front", lay, EXT)
    gaps = gap_positions(tr["box"])
    right = _as_prediction(tr)
    right["box_raw"], right["gap"] = right["box"], torch.where(gaps, 20.0, -20.0)
    right["box"] = cut_at_gaps(right["box_raw"], right["gap"])
    blind = {**right, "gap": -right["gap"]}            # calls every gap a non-gap and every box a gap
    assert structure_loss("front", right, lay, EXT) < 1e-3
    assert structure_loss("front", blind, lay, EXT) > 5.0
    assert structure_loss("front", {k: v for k, v in right.items() if k not in ("gap", "box_raw")}, lay, EXT) < 1e-3
    # --gap-loss-weight scales the gap term alone: at 0 a blind gap output costs nothing more
    off, one, three = (float(structure_loss("front", blind, lay, EXT, gap_loss_weight=w)) for w in (0.0, 1.0, 3.0))
    assert off == pytest.approx(float(structure_loss("front", right, lay, EXT, gap_loss_weight=0.0)), abs=1e-3)
    assert three - off == pytest.approx(3 * (one - off), rel=1e-4)


def _struct_net(R=3, img=64, lay=S, **cfg):
    torch.manual_seed(0)
    net = RackLayNet(ModelConfig(R=R, image_size=img, layout_size=lay, decoder="struct", **cfg)).eval()
    for dec in net.decoders.values():       # make boxes likely so the outputs are not all shelf
        with torch.no_grad():
            dec.pos_head.bias[0] = 2.0
            dec.pos_head.weight.normal_(0, 0.05)
    return net


def test_struct_decoder_draws_boxes_as_rectangles_standing_on_their_board():
    """Front view of a struct model: in every column a box is one run of rows starting at the board
    (row S/2 - 1 upward), and box pixels lie inside the shelf's free space."""
    net = _struct_net()
    with torch.no_grad():
        out = net(torch.randn(2, 3, 64, 64))
    front = out["front"].argmax(2).numpy()
    assert (front == L.BOX).any()
    for img in front:
        for ch in img:
            for col in ch.T:
                rows = np.nonzero(col == L.BOX)[0]
                if rows.size:
                    assert rows.max() == S // 2 - 1 and rows.size == rows.max() - rows.min() + 1


def test_struct_decoder_shelf_length_changes_the_scale_and_not_the_shape():
    net = _struct_net()
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        base, st = net(x, with_structure=True)
        known = net(x, shelf_length=1.2)
    for v in ("top", "front"):
        lengths = L.shelf_lengths(known[v].argmax(2)[0].numpy(), G)
        assert lengths[0] == pytest.approx(1.2, abs=2 * G.res)
        # shape: the fraction of the shelf's columns holding a box is unchanged
        fa, fb = ((a.argmax(2)[0, 0] == L.BOX).any(0).sum() / (a.argmax(2)[0, 0] > 0).any(0).sum()
                  for a in (base[v], known[v]))
        assert float(fa) == pytest.approx(float(fb), abs=0.05)
    assert set(st) == {"top", "front"} and st["front"]["height"].shape == (1, 3, st["front"]["box"].shape[-1])


def test_struct_views_agree_on_which_shelves_exist_their_length_and_where_boxes_stand():
    """Top and front view are one board seen twice: a struct RackLay-D model draws each shelf
    channel over the same columns in both views and boxes in the same columns, even where the
    two views' heads alone would not (here: 1.5 m against 3 m, boxes mostly against rarely)."""
    net = _struct_net()
    with torch.no_grad():
        for v, length, box in (("top", 1.5, 2.0), ("front", 3.0, -1.0)):
            dec = net.decoders[v]
            dec.shelf_head.bias[1] = math.log(length)
            dec.pos_head.bias[0] = box
            dec.pos_head.weight.normal_(0, 0.5)
        out = net(torch.randn(2, 3, 64, 64))
    top, front = (out[v].argmax(2).numpy() for v in ("top", "front"))
    assert (front == L.BOX).any()
    for cls in (L.SHELF, L.BOX):           # shelf: any non-background pixel in the column
        cols = [((a > 0) if cls == L.SHELF else (a == L.BOX)).any(2) for a in (top, front)]
        assert np.array_equal(*cols)


def test_struct_structure_loss_trains_every_part_of_the_decoder():
    net = _struct_net().train()
    top, front = _two_box_shelf()
    out, st = net(torch.randn(2, 3, 64, 64), with_structure=True)
    loss = sum(structure_loss(v, st[v], torch.from_numpy(a)[None].long().expand(2, -1, -1, -1), EXT)
               for v, a in (("top", top), ("front", front)))
    loss.backward()
    for name, p in net.decoders.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert any(p.grad.abs().sum() > 0 for p in net.encoder.parameters())


# --- the known-dimension scale of any model's layouts -------------------------------------------


def test_scaling_a_shelf_about_its_origin_is_the_shelf_drawn_at_that_size():
    top, front = _two_box_shelf(length=2.0)
    f = L.length_factors([top, front], G, 1.0)
    assert f.tolist() == [0.5, 0.5, 1.0]
    small_top, small_front = _two_box_shelf(length=1.0, depth=0.4, clear=0.25)
    for big, small in ((top, small_top), (front, small_front)):
        got = L.scale_about_origin(big, f)
        assert (got[0] != small[0]).mean() < 0.005          # edge pixels may round differently
        assert _runs((got[0] == L.BOX).any(0)) == 2
        assert not got[2].any()
    assert np.array_equal(L.scale_about_origin(top, [1.0, 1.0, 1.0]), top)
    with pytest.raises(ValueError, match="positive"):
        L.scale_about_origin(top, [0.0, 1.0, 1.0])


def test_box_runs_counts_boxes_with_a_gap_as_two_and_touching_ones_as_one():
    top, front = _two_box_shelf()
    assert L.box_runs(front).tolist() == [2, 0, 0] and L.box_runs(top).tolist() == [2, 0, 0]
    touching = [L.Box(-0.3, 0.0, 0.4, 0.5, 0.3), L.Box(0.1, 0.0, 0.4, 0.5, 0.3)]   # x in [-0.5, -0.1] and [-0.1, 0.3]
    f = L.rasterize_shelf(L.Shelf(2.0, 0.8, 0.5), touching, G).front
    assert L.box_runs(f) == 1


def test_a_separation_counts_only_on_the_shelf_the_truth_separates():
    _, front = _two_box_shelf()                    # channel 0: two boxes apart
    bridged = front[0].copy()                      # the gap painted over: one run
    cols = np.nonzero((bridged == L.BOX).any(0))[0]
    bridged[np.ix_((bridged == L.BOX).any(1), np.arange(cols[0], cols[-1] + 1))] = L.BOX
    assert L.box_runs(bridged) == 1
    elsewhere = np.stack([bridged, front[0], front[2]])     # separated, but on channel 1
    t, p, hit, _ = L.separated_shelves(front, front)
    assert t.tolist() == [True, False, False] and hit.tolist() == [True, False, False]
    t, p, hit, placed = L.separated_shelves(front, elsewhere)
    assert p.tolist() == [False, True, False] and not hit.any() and not placed.any()


def test_a_separation_is_placed_only_when_a_predicted_gap_is_at_a_true_one():
    _, front = _two_box_shelf()                    # channel 0: two boxes apart
    assert L.separated_shelves(front, front).placed.tolist() == [True, False, False]
    (lo, hi), = L.box_gaps(front[0])
    assert 0 < lo < hi < 1
    # the boxes bridged, then cut near the right end, far from the true gap: a hit, not placed
    moved = front[0].copy()
    cols = np.nonzero((moved == L.BOX).any(0))[0]
    moved[np.ix_((moved == L.BOX).any(1), np.arange(cols[0], cols[-1] + 1))] = L.BOX
    cut = moved[:, cols[-1] - 3:cols[-1] - 1]
    cut[cut == L.BOX] = L.SHELF
    (plo, phi), = L.box_gaps(moved)
    assert plo > hi + L.GAP_TOLERANCE
    far = np.stack([moved, front[1], front[2]])
    sep = L.separated_shelves(front, far)
    assert sep.hit.tolist() == [True, False, False] and not sep.placed.any()


def test_shelf_length_ignores_stray_pixels_beside_the_shelf():
    top, _ = _two_box_shelf(length=2.0)
    top[0, 10, 3:6] = L.BOX                          # a stray blob far to the left
    assert L.shelf_lengths(top, G)[0] == pytest.approx(2.0, abs=G.res)


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    return make_toy(tmp_path_factory, n=6, seed=5, R=3, D=128)


@pytest.fixture(scope="module")
def struct_ckpt(tmp_path_factory):
    from racklay.checkpoint import save_checkpoint

    net = _struct_net(R=3, img=64, lay=64)
    cfg = net.cfg
    path = tmp_path_factory.mktemp("struct") / "struct.safetensors"
    save_checkpoint(path, net, cfg)
    return path


def test_predict_shelf_length_rescales_every_shelf_and_says_so(toy, struct_ckpt, tmp_path, capsys):
    photo = str(toy / "Images" / "000000.png")
    assert racklay_main(["predict", photo, "--weights", str(struct_ckpt), "--out", str(tmp_path / "a"),
                         "--no-figure", "--no-png"]) == 0
    assert racklay_main(["predict", photo, "--weights", str(struct_ckpt), "--out", str(tmp_path / "b"),
                         "--no-figure", "--no-png", "--shelf-length", "1.5"]) == 0
    assert "shelves scaled to 1.5 m" in capsys.readouterr().out
    g = L.Grid(64, EXT)
    for v in ("top", "front"):
        a = _layouts(tmp_path / "a", v)
        b = _layouts(tmp_path / "b", v)
        have = L.shelf_lengths(b, g)
        assert all(x == pytest.approx(1.5, abs=2 * g.res) for x, y in zip(have, L.shelf_lengths(a, g)) if y > 0)
    meta = json.loads((tmp_path / "b" / "meta" / "000000.json").read_text())
    assert meta["shelf_length_m"] == 1.5
    # a known load width changes the figure's outlines only: the same layouts, recorded in the meta
    assert racklay_main(["predict", photo, "--weights", str(struct_ckpt), "--out", str(tmp_path / "w"),
                         "--no-png", "--shelf-length", "1.5", "--load-width", "0.5"]) == 0
    assert json.loads((tmp_path / "w" / "meta" / "000000.json").read_text())["load_width_m"] == 0.5
    assert (tmp_path / "w" / "figures" / "000000.png").is_file()
    for v in ("top", "front"):
        assert np.array_equal(_layouts(tmp_path / "w", v), _layouts(tmp_path / "b", v))
    with pytest.raises(SystemExit):
        racklay_main(["predict", photo, "--weights", str(struct_ckpt), "--out", str(tmp_path / "c"),
                      "--shelf-length", "-2"])
    assert "--shelf-length" in capsys.readouterr().err


def test_predict_says_where_the_frame_cuts_a_shelf(toy, tmp_path, capsys):
    """A struct model's placement says where each shelf lies across the photo: `racklay predict`
    writes it to the meta (`shelf_spans_image`, image widths) and, where a shelf runs out of the
    frame, notes that its length (the metric scale) is inferred, not seen, unless --shelf-length
    fixes it; `racklay analyze` warns the same; a shelf inside the frame gets no note."""
    from racklay.checkpoint import save_checkpoint

    photo = str(toy / "Images" / "000000.png")
    for half in (0.3, 0.8):                  # spans [0.2, 0.8] (inside) and [-0.3, 1.3] (cut at both ends)
        net = _struct_net(R=3, img=64, lay=64)
        with torch.no_grad():
            for dec in net.decoders.values():
                dec.shelf_head.weight[[0, 3, 4]] = 0.0
                dec.shelf_head.bias[[0, 3, 4]] = torch.tensor([5.0, 0.0, math.log(half)])
        ck = save_checkpoint(tmp_path / f"half{half}.safetensors", net, net.cfg)
        for extra in ([], ["--shelf-length", "1.5"]):
            out = tmp_path / f"o{half}{len(extra)}"
            assert racklay_main(["predict", photo, "--weights", str(ck), "--out", str(out), "--no-figure",
                                 "--no-png", *extra]) == 0
            err = capsys.readouterr().err
            spans = json.loads((out / "meta" / "000000.json").read_text())["shelf_spans_image"]
            assert spans == [pytest.approx([0.5 - half, 0.5 + half], abs=1e-3)] * 3
            cut = half > 0.5 and not extra
            assert ("000000.png: the frame cuts shelf 1 (both ends), shelf 2 (both ends), shelf 3 (both ends)"
                    in err) == cut
            assert ("the frame cuts a shelf in 1 of 1 photo(s)" in err and "--shelf-length fixes the scale" in err) == cut
            # analyze's metric sizes and volumes rest on the same scale: it warns too
            assert racklay_main(["analyze", photo, "--weights", str(ck), "--out", str(out) + "_an", "--no-render",
                                 *extra]) == 0
            err = capsys.readouterr().err
            assert ("warning: " + photo + ": the frame cuts shelf 1 (both ends)" in err) == cut


def test_frame_cuts_names_each_shelf_that_reaches_the_frame_edge():
    from racklay.predict import FRAME_EDGE_MARGIN, frame_cuts
    from racklay.torchdata import padded_columns, photo_columns

    m = FRAME_EDGE_MARGIN
    spans = np.array([[m / 2, 0.7], [m * 1.5, 1 - m * 1.5], [0.3, 1.2], [np.nan, np.nan], [-0.4, 1.0]])
    assert frame_cuts(spans) == ["shelf 1 (left end)", "shelf 3 (right end)", "shelf 5 (both ends)"]
    # a letterboxed photo's spans are read back in the photo's widths: its edges at 0 and 1
    x = np.array([-0.2, 0.0, 0.37, 1.0])
    assert photo_columns(padded_columns(x, 170, 256), 170, 256) == pytest.approx(x, abs=1e-6)


def test_scale_cues_bench_prints_its_tables_and_plot(toy, struct_ckpt, tmp_path, capsys):
    """bench/accuracy/scale_cues.py on a set without WareSynth meta: the size tables, the framing
    group "unknown" scored, and the plot written."""
    from bench.accuracy.scale_cues import main as scale_cues

    out = tmp_path / "scale.png"
    assert scale_cues(["--weights", str(struct_ckpt), "--data", str(toy), "--n", "4", "--iou", "--plot", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| all | " in text and "shelf length (front view)" in text
    assert "| no level spans in the meta | 1 |" in text       # the toy set's test split: one image
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_eval_scale_from_truth_scores_shape_alone(toy, struct_ckpt, tmp_path, capsys):
    """A prediction that is the truth at twice its size scores low on the metric IoU and 1 with
    --scale-from-truth; the JSON says which scale was scored."""
    from racklay.data import RackLayRoot
    from racklay.evaluate import evaluate
    from racklay.predict import Predictor

    fake = Predictor(struct_ckpt)
    first = RackLayRoot(toy).resolve("test")[:1]

    def twice_the_truth(x):
        """The truth of the split's first image scaled x2 (probabilities one-hot)."""
        out_c, out_p = {}, {}
        for v in fake.views:
            truth = np.stack([L.resize_layouts(_layouts(toy, v, i), fake.layout_size) for i in first])
            c = np.stack([L.scale_about_origin(t, [2.0] * 3) for t in truth])
            out_c[v] = c
            out_p[v] = np.moveaxis(np.eye(3, dtype=np.float32)[c], -1, 2)
        return out_c, out_p

    fake.predict_batch = twice_the_truth
    metric = evaluate(fake, toy, split="test", limit=1, progress=False, batch_size=1)
    shape = evaluate(fake, toy, split="test", limit=1, progress=False, batch_size=1, scale_from_truth=True)
    for v in ("top", "front"):
        assert metric[v]["dataset"]["shelf"]["IoU"] < 0.5
        assert shape[v]["dataset"]["shelf"]["IoU"] > 0.9
    out = tmp_path / "e.json"
    assert racklay_main(["eval", "--weights", str(struct_ckpt), "--data", str(toy), "--split", "test",
                         "--scale-from-truth", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["scale"] == "from truth"
    assert "scale from truth" in capsys.readouterr().out


def _layouts(root, view, sid="000000"):
    from racklay.data import RackLayRoot

    return RackLayRoot(root).read_layouts(view, sid, R=3)


def _exported_predicts_the_same(ckpt, tmp_path) -> None:
    """`racklay export --onnx` of a checkpoint predicts the checkpoint's layouts (64 x 64 inputs)."""
    from racklay.predict import Predictor

    out = tmp_path / "model.onnx"
    assert racklay_main(["export", "--weights", str(ckpt), "--onnx", str(out)]) == 0
    x = torch.randn(2, 3, 64, 64)
    a, b = Predictor(ckpt).predict_batch(x)[0], Predictor(out).predict_batch(x)[0]
    for v in ("top", "front"):
        assert (a[v] == b[v]).mean() > 0.999


def test_struct_model_exports_to_onnx_with_the_same_layouts(struct_ckpt, tmp_path):
    _exported_predicts_the_same(struct_ckpt, tmp_path)


def test_struct_model_with_a_back_interval_exports_to_onnx_and_draws_the_same(tmp_path):
    from racklay.checkpoint import save_checkpoint

    net = _struct_net(R=2, img=64, lay=64, struct_back=True)
    back = net.decoders["top"].back_head
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():                   # a box behind the front one at most positions, to the back edge
        back.weight.normal_(0, 0.05)
        back.bias.copy_(torch.tensor([-100.0, 1.5, 4.0]))
        none = net(x)["top"].argmax(2)
        back.bias[0] = 4.0
        assert (net(x)["top"].argmax(2) != none).any(), "the back interval drew nothing"
    _exported_predicts_the_same(save_checkpoint(tmp_path / "back.safetensors", net, net.cfg), tmp_path)


def test_struct_model_with_a_gap_output_exports_to_onnx_and_its_cuts_show(tmp_path):
    from racklay.checkpoint import save_checkpoint
    from racklay.predict import Predictor

    net = _struct_net(R=3, img=64, lay=64, struct_gap=True)     # boxes likely everywhere
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        for dec in net.decoders.values():   # no gap called yet
            dec.gap_head.weight.normal_(0, 30.0)
            dec.gap_head.bias.fill_(-100.0)
        assert (L.box_runs(net(x)["front"].argmax(2).numpy()) == 1).all()
        gap = net(x, with_structure=True)[1]["front"]["gap"] + 100.0
        for dec in net.decoders.values():   # now half the positions are called gaps
            dec.gap_head.bias.fill_(-float(gap.median()))
    ck = save_checkpoint(tmp_path / "gap.safetensors", net, net.cfg)
    out = tmp_path / "gap.onnx"
    assert racklay_main(["export", "--weights", str(ck), "--onnx", str(out)]) == 0
    a, b = Predictor(ck).predict_batch(x)[0], Predictor(out).predict_batch(x)[0]
    for v in ("top", "front"):
        assert (a[v] == b[v]).mean() > 0.999
    assert (L.box_runs(a["front"]) >= 2).any(), "the gap output cut no box run"
