"""The annotation tool's server logic (annotate.editor.Tool) without a browser: the click workflow,
editing, undo/redo, conflicts between two labellers, invalid files, and model-assisted
proposals with a stand-in predictor that follows racklay.predict.Predictor's contract."""
import os

import numpy as np
import pytest

from annotate import draw as D
from annotate import geometry as G
from annotate.app import build_app
from annotate.editor import Tool
from annotate.store import Project
from racklay import layout as L
from racklay.atomic import encode_png
from test_annotate_geometry import BOARDS, BOXES, GRID, Camera, clicks, iou, true_layouts

CAM = Camera([-1.2, -2.4, 1.6], [1.0, 0.0, 0.9])


@pytest.fixture
def proj(tmp_path):
    (tmp_path / "r.png").write_bytes(encode_png(np.full((480, 640, 3), 90, np.uint8)))
    p = Project(tmp_path)
    p.save_settings(dict(p.settings, D=256, extent=4.0))
    return p


def disp(tool, st, pt):
    """Where the page sends a click on photo pixel pt: the page maps its zoom and pan to photo
    pixels itself (tests/test_annotate_browser.py checks that), so the server gets pt."""
    return pt[0], pt[1]


def label_by_clicks(tool, st, ann):
    for c in ann["rack"]["corners"]:
        st = tool.click(st, *disp(tool, st, c))
    assert st.mode == "shelves"
    for s in ann["shelves"]:
        st = tool.click(st, *disp(tool, st, s["point"]))
    st.mode = "boxes"
    for b in ann["boxes"]:
        st = tool.click(st, *disp(tool, st, b["p0"]))
        st = tool.click(st, *disp(tool, st, b["p1"]))
    return st


def test_click_workflow_matches_ground_truth(proj):
    tool = Tool(proj)
    st = tool.open("r.png")
    truth = clicks(CAM)
    st = label_by_clicks(tool, st, truth)
    for b, t in zip(st.ann["boxes"], truth["boxes"]):  # depth / offset are typed per box
        st.sel = ["box", b["id"]]
        st = tool.set_box_field(st, "depth", t["depth"])
        st = tool.set_box_field(st, "front_offset", t["front_offset"])
        if t.get("on_board") is False:  # the box resting on something: the labeller says so (f)
            st = tool.toggle_on_board(st)
    saved = proj.load("r.png")
    assert saved["status"] == "in progress" and len(saved["boxes"]) == len(BOXES)
    _, top, front = tool.layouts(saved)
    ttop, tfront = true_layouts()
    for i in range(3):
        assert iou(top[i] == L.BOX, ttop[i] == L.BOX) >= 0.9
        assert iou(front[i] == L.BOX, tfront[i] == L.BOX) >= 0.9
    f = tool.frame(st)
    assert D.preview(f).ndim == 3
    shapes = D.overlay(f)   # drawn over the photo by the page: rack, 3 shelf lines, every box
    assert sum(s["t"] == "poly" for s in shapes) == 1 + 3 + len(BOXES)
    assert "S3" in D.summary(f) and "0 of 1 done" in D.header(f)


def test_select_move_resize_delete_undo_redo(proj):
    tool = Tool(proj)
    st = label_by_clicks(tool, tool.open("r.png"), clicks(CAM))
    b0 = dict(st.ann["boxes"][0])
    centre = [(b0["p0"][0] + b0["p1"][0]) / 2, (b0["p0"][1] + b0["p1"][1]) / 2]
    st.mode = "select"
    st = tool.click(st, *disp(tool, st, centre))
    assert st.sel == ["box", 0]
    st.mode = "move"
    st = tool.click(st, *disp(tool, st, [centre[0] + 10, centre[1]]))
    moved = st.ann["boxes"][0]
    assert moved["p0"][0] == pytest.approx(b0["p0"][0] + 10, abs=0.05)
    st.mode = "resize"   # click near a corner (grab), then where it goes
    st = tool.click(st, *disp(tool, st, [moved["p1"][0] - 2, moved["p1"][1] + 1]))
    assert st.grab is not None and st.ann["boxes"][0] == moved
    st = tool.click(st, *disp(tool, st, [moved["p1"][0] + 7, moved["p1"][1]]))
    assert st.ann["boxes"][0]["p1"][0] == pytest.approx(moved["p1"][0] + 7, abs=0.05)
    assert st.ann["boxes"][0]["p0"] == moved["p0"] and st.grab is None
    n = len(st.ann["boxes"])
    st = tool.delete(st)
    assert len(proj.load("r.png")["boxes"]) == n - 1
    st = tool.undo(st)
    assert len(proj.load("r.png")["boxes"]) == n
    assert proj.load("r.png")["boxes"][0]["p1"][0] == pytest.approx(moved["p1"][0] + 7, abs=0.05)
    st = tool.undo(st, redo=True)
    assert len(proj.load("r.png")["boxes"]) == n - 1
    # a shelf line and a corner can be picked too
    st.mode = "select"
    st = tool.click(st, *disp(tool, st, st.ann["rack"]["corners"][0]))
    assert st.sel == ["corner", 0]


def test_resize_moves_the_corner_grabbed_even_past_the_middle(proj):
    """Shrinking a wide box by dragging its right edge far to the left moves the right corner
    (not the left one, which is nearer to where it lands); a drag in select mode grabs a box by
    its corner, by its inside it moves it."""
    tool = Tool(proj)
    st = tool.open("r.png")
    st.mode = "boxes"
    st = tool.drag(st, [100, 200], [500, 300])
    assert st.sel == ["box", 0]
    st.mode = "resize"
    st = tool.drag(st, [499, 299], [180, 260])          # right-bottom corner to near the left edge
    b = st.ann["boxes"][0]
    assert b["p0"] == [100, 200] and b["p1"] == [180, 260]
    st.mode = "select"
    st = tool.drag(st, [101, 201], [90, 190])           # grabbed by its top-left corner: resized
    b = st.ann["boxes"][0]
    assert b["p0"] == [90, 190] and b["p1"] == [180, 260]
    st = tool.drag(st, [140, 230], [150, 240])          # grabbed inside: moved by the drag
    b = st.ann["boxes"][0]
    assert b["p0"] == [100, 200] and b["p1"] == [190, 270]
    st.mode = "move"
    st = tool.drag(st, [0, 0], [-10, 5])
    assert st.ann["boxes"][0]["p0"] == [90, 205]
    st = tool.undo(st)
    assert st.ann["boxes"][0]["p0"] == [100, 200]
    # the page sends drags as actions; one made on another photo is not applied
    st = tool.apply(st, [{"kind": "drag", "p0": [0, 0], "p1": [10, 0], "image": "other.png", "seq": 1}])
    assert "not applied" in st.msg and st.ann["boxes"][0]["p0"] == [100, 200]


def test_rack_size_from_a_reference_object_of_known_size(proj):
    """A labeller who knows one object's size (a pallet's front: 1.2 m wide) draws its box and
    presses g: the rack's width and height follow from the rack plane, whatever size was guessed."""
    truth = clicks(CAM)
    W, H = truth["rack"]["width"], truth["rack"]["height"]
    tool = Tool(proj)
    st = label_by_clicks(tool, tool.open("r.png"), dict(truth, boxes=[]))
    st = tool.set_rack(st, width=W * 1.7, height=H * 0.6)     # a wrong guess
    guessed = dict(st.ann["rack"])
    # the true box 0's front face, outlined on the photo (its true size known to the labeller)
    _, x0, x1, z0, z1 = BOXES[0][:5]
    b0 = truth["boxes"][0]
    st.mode = "boxes"
    st = tool.drag(st, b0["p0"], b0["p1"])
    st = tool.size_from_box(st)
    assert "type the reference" in st.msg
    st = tool.set_field(st, "ref_width", f"{x1 - x0:g}")
    st = tool.set_field(st, "ref_height", "")
    st = tool.size_from_box(st)
    r = proj.load("r.png")["rack"]
    assert r["width"] == pytest.approx(W, rel=0.02) and r["height"] == guessed["height"]
    assert r["size_confirmed"] is True and "height unchanged" in st.msg
    st = tool.set_field(st, "ref_height", "abc")
    assert "not a number" in st.msg
    st = tool.set_field(st, "ref_height", f"{z1 - z0:g}")
    st = tool.size_from_box(st)
    r = proj.load("r.png")["rack"]
    assert r["width"] == pytest.approx(W, rel=0.02) and r["height"] == pytest.approx(H, rel=0.02)


def test_a_box_around_a_row_of_equal_loads_splits_into_n_on_the_rack_plane(proj):
    """One box drawn around a row (or an accepted one-per-shelf proposal), N typed, `w`: N boxes
    of equal metric width side by side (split on the rack plane, not in pixels of an oblique
    photo), each keeping the box's depth and flags; undo gives the one box back."""
    tool = Tool(proj)
    truth = clicks(CAM)
    st = label_by_clicks(tool, tool.open("r.png"), dict(truth, boxes=[]))
    s_, x0, x1, z0, z1, o = 1, 0.20, 0.90, 0.0, 0.50, 0.0   # BOXES[3]
    p = CAM.project([[x0, o, BOARDS[s_] + z0], [x1, o, BOARDS[s_] + z1]])
    st.mode = "boxes"
    st = tool.drag(st, p[0].tolist(), p[1].tolist())
    st = tool.set_box_field(st, "depth", 0.4)
    st = tool.set_field(st, "split_n", "2.5")
    assert "whole number" in st.msg
    st = tool.set_field(st, "split_n", "3")
    st = tool.apply(st, [{"kind": "act", "name": "split_row", "seq": 1}])
    boxes = proj.load("r.png")["boxes"]
    assert len(boxes) == 3 and all(b["depth"] == 0.4 for b in boxes) and st.sel == ["box", boxes[0]["id"]]
    scene = G.build_scene(proj.load("r.png"), proj.settings)
    spans = sorted((m.u0, m.u1, m.shelf) for m in scene.boxes)
    np.testing.assert_allclose([sp[:2] for sp in spans], [[0.20, 0.4333], [0.4333, 0.6667], [0.6667, 0.90]], atol=0.01)
    assert {sp[2] for sp in spans} == {s_}
    st = tool.undo(st)
    assert len(proj.load("r.png")["boxes"]) == 1



def slot_photo(plane, slots, v0: float, v1: float) -> bytes:
    """A 640 x 480 light grey photo (PNG bytes) with a dark slot over each (u0, u1) of `slots`
    from v0 to v1 on the rack plane (as seen through `plane`): gaps between loads."""
    import cv2

    rgb = np.full((480, 640, 3), 170, np.uint8)
    for u0, u1 in slots:
        q = plane.to_image([[u0, v0], [u1, v0], [u1, v1], [u0, v1]])
        cv2.fillPoly(rgb, [np.round(q).astype(np.int32)], (35, 35, 35))
    return encode_png(rgb)


def test_a_box_around_a_row_splits_where_the_photo_shows_gaps(proj):
    """One box drawn around loads of unequal widths, `W`: cut at the two dark slots the photo shows
    between them (on the rack plane of an oblique photo), each part keeping the box's depth;
    a photo with no slot along the box leaves it whole and says why."""
    truth = clicks(CAM)
    plane = G.build_scene(truth, proj.settings).plane
    s_, x0, x1, top = 2, 0.50, 1.50, 0.45                       # BOXES[5]'s front face
    (proj.root / "gaps.png").write_bytes(slot_photo(plane, [(0.78, 0.82), (1.10, 1.16)], BOARDS[s_], BOARDS[s_] + top))
    tool = Tool(proj)
    for name in ("r.png", "gaps.png"):
        st = label_by_clicks(tool, tool.open(name), dict(truth, image=name, boxes=[]))
        p = CAM.project([[x0, 0.0, BOARDS[s_]], [x1, 0.0, BOARDS[s_] + top]])
        st.mode = "boxes"
        st = tool.drag(st, p[0].tolist(), p[1].tolist())
        st = tool.set_box_field(st, "depth", 0.4)
        st = tool.apply(st, [{"kind": "act", "name": "split_at_gaps", "seq": 1}])
        boxes = proj.load(name)["boxes"]
        if name == "r.png":                                      # an even grey photo: no gap to cut at
            assert len(boxes) == 1 and "no gap" in st.msg
            continue
        assert len(boxes) == 3 and all(b["depth"] == 0.4 for b in boxes), st.msg
        spans = sorted((m.u0, m.u1, m.shelf) for m in G.build_scene(proj.load(name), proj.settings).boxes)
        np.testing.assert_allclose([sp[:2] for sp in spans], [[0.50, 0.78], [0.82, 1.10], [1.16, 1.50]], atol=0.015)
        assert {sp[2] for sp in spans} == {s_}


def test_every_key_and_button_action_is_one_the_tool_knows(proj):
    """Each action the page's keys and buttons send (annotate.page KEYMAP, BUTTONS; modes and view
    changes stay in the page) is applied by the tool, not refused as unknown, on a photo with
    nothing marked yet; and every button has its element on the page."""
    from annotate.page import BUTTONS, KEYMAP

    tool = Tool(proj)
    acts = sorted({a for a in list(KEYMAP.values()) + list(BUTTONS.values()) if ":" not in a})
    assert {"split_row", "split_at_gaps", "accept", "done"} <= set(acts)
    for seq, name in enumerate(acts, 1):
        st = tool.apply(tool.open("r.png"), [{"kind": "act", "name": name, "seq": seq}])
        assert "unknown" not in st.msg, (name, st.msg)
    html = build_app(proj).config["components"]
    ids = {c.get("props", {}).get("elem_id") for c in html}
    missing = [b for b in BUTTONS if b not in ids and not b.startswith("mode-") and not b.startswith("btn-zoom")]
    assert not missing, missing

def test_two_labellers_conflict_is_refused_with_message(proj):
    ana, ben = Tool(proj, user="ana"), Tool(proj, user="ben")
    sa, sb = ana.open("r.png"), ben.open("r.png")
    sa = ana.click(sa, 100, 100)
    sb = ben.click(sb, 300, 300)
    assert "⚠" in sb.msg and "ana changed this image meanwhile" in sb.msg
    assert proj.load("r.png")["rack"]["corners"] == [[100, 100]]
    sb = ben.open("r.png")  # reloading shows ana's work, and ben can go on
    sb = ben.click(sb, 300, 300)
    assert len(proj.load("r.png")["rack"]["corners"]) == 2


def test_invalid_file_is_shown_not_overwritten(proj):
    p = proj.annotation_path("r.png")
    p.parent.mkdir(exist_ok=True)
    p.write_text("{broken")
    tool = Tool(proj)
    st = tool.open("r.png")
    assert "not valid JSON" in st.msg and st.ann is None
    st = tool.click(st, 10, 10)
    assert p.read_text() == "{broken"


class StandIn:
    """Follows racklay.predict.Predictor's contract; returns the true scene's layouts."""

    def __init__(self, scale: float = 1.0):
        self.calls, self.scale, self.shapes, self.boxes = 0, scale, [], []

    def predict(self, rgb, rack_box=None, source="image"):
        assert rgb.dtype == np.uint8 and rgb.ndim == 3
        self.calls += 1
        self.shapes.append(rgb.shape)
        self.boxes.append(rack_box)
        top, front = (L.scale_about_origin(a, [self.scale] * len(a)) for a in true_layouts())
        probs = {v: np.eye(3, dtype=np.float32)[a].transpose(0, 3, 1, 2) for v, a in (("top", top), ("front", front))}
        return {"top": top, "front": front, "probs": probs, "grid": GRID}


def test_proposals_take_their_scale_from_the_labellers_rack_width(proj):
    """A model that gets the rack's shape right but its size 25 % too large (one photo cannot tell):
    the labeller's rack width fixes the scale, so every proposal lands on its true box."""
    tool = Tool(proj, predictor=StandIn(scale=1.25))
    truth = clicks(CAM)
    truth["boxes"] = []
    st = label_by_clicks(tool, tool.open("r.png"), truth)
    props = st.ann["proposals"]
    assert len(props) == len(BOXES)
    scene = G.build_scene(st.ann, proj.settings)
    got = sorted((m.shelf, m.u0, m.u1) for m in (G.metric_box(scene.plane, p, scene.shelf_v, 0.6, 0.6) for p in props))
    want = sorted((s, x0, x1) for s, x0, x1, *_ in BOXES)
    assert [g[0] for g in got] == [w[0] for w in want]
    np.testing.assert_allclose([g[1:] for g in got], [w[1:] for w in want], atol=3 * GRID.res)


def test_model_proposals_accept_edit_reject(proj):
    pred = StandIn()
    tool = Tool(proj, predictor=pred)
    truth = clicks(CAM)
    truth["boxes"] = []
    st = label_by_clicks(tool, tool.open("r.png"), truth)
    props = st.ann["proposals"]
    assert len(props) == len(BOXES) and pred.calls == 1  # predicted once, cached
    # each proposal, mapped back through the geometry, is the true box
    scene = G.build_scene(st.ann, proj.settings)
    got = sorted((G.metric_box(scene.plane, p, scene.shelf_v, 0.6, 0.6).shelf, p["depth"]) for p in props)
    want = sorted((s, d) for s, *_, d in BOXES)
    assert [g[0] for g in got] == [w[0] for w in want]
    np.testing.assert_allclose([g[1] for g in got], [w[1] for w in want], atol=2 * GRID.res)
    # select one proposal by clicking inside it, accept it
    p = props[0]
    st.mode = "select"
    st = tool.click(st, *disp(tool, st, [(p["p0"][0] + p["p1"][0]) / 2, (p["p0"][1] + p["p1"][1]) / 2]))
    assert st.sel == ["proposal", p["id"]]
    st = tool.accept(st)
    assert len(st.ann["boxes"]) == 1 and st.ann["boxes"][0]["source"] == "model"
    assert st.sel == ["box", st.ann["boxes"][0]["id"]]   # the accepted box stays selected, to edit
    assert len(st.ann["proposals"]) == len(BOXES) - 1
    # reject the next one: it is remembered and not proposed again when a shelf moves
    q = st.ann["proposals"][0]
    st.sel = ["proposal", q["id"]]
    st = tool.reject(st)
    assert len(st.ann["rejected"]) == 1
    shelf = st.ann["shelves"][0]
    st.sel, st.mode = ["shelf", shelf["id"]], "move"
    st = tool.click(st, *disp(tool, st, [shelf["point"][0] + 0.4, shelf["point"][1]]))
    assert len(st.ann["proposals"]) == len(BOXES) - 2
    st = tool.accept(st, all_=True)
    assert len(st.ann["boxes"]) == len(BOXES) - 1 and not st.ann["proposals"]
    assert pred.calls == 1



def test_a_proposal_over_two_loads_is_cut_at_the_gap_the_photo_shows(proj):
    """The model reads the top shelf's 1 m load as one; the photo shows a dark slot across its
    middle (two loads): the tool proposes the two, split at the slot, unless the cut is off."""
    truth = clicks(CAM)
    photo = slot_photo(G.build_scene(truth, proj.settings).plane, [(0.97, 1.03)], BOARDS[2], BOARDS[2] + 0.45)
    for depth, want in ((G.GapSplit().depth, len(BOXES) + 1), (0.0, len(BOXES))):
        name = f"slot{depth:g}.png"
        (proj.root / name).write_bytes(photo)
        tool = Tool(proj, predictor=StandIn())
        tool.gap_split = G.GapSplit(depth=depth)
        st = label_by_clicks(tool, tool.open(name), dict(truth, image=name, boxes=[]))
        scene = G.build_scene(st.ann, proj.settings)
        top = sorted((m.u0, m.u1) for m in (G.metric_box(scene.plane, p, scene.shelf_v, 0.6, 0.6)
                                            for p in st.ann["proposals"]) if m.shelf == 2)
        assert len(st.ann["proposals"]) == want
        if depth:
            np.testing.assert_allclose(top, [(0.5, 0.97), (1.03, 1.5)], atol=0.03)
        else:
            np.testing.assert_allclose(top, [(0.5, 1.5)], atol=0.03)

def test_done_asks_once_then_rejects_waiting_proposals(proj):
    """d while model proposals wait: the first press asks, any other action disarms it, a
    second d right after rejects them all (remembered) and marks the photo done."""
    tool = Tool(proj, predictor=StandIn())
    truth = clicks(CAM)
    st = label_by_clicks(tool, tool.open("r.png"), dict(truth, boxes=[]))
    st = tool.confirm_size(st)
    n = len(st.ann["proposals"])
    assert n == len(BOXES)
    d = {"kind": "act", "name": "done"}
    st = tool.apply(st, [dict(d, seq=1)])
    assert "press d again" in st.msg and len(st.ann["proposals"]) == n and st.ann["status"] != "done"
    st = tool.apply(st, [{"kind": "mode", "mode": "select", "seq": 2}, dict(d, seq=3)])
    assert "press d again" in st.msg and len(st.ann["proposals"]) == n      # disarmed, asked again
    st = tool.apply(st, [dict(d, seq=4)])
    saved = proj.load("r.png")
    assert not saved["proposals"] and len(saved["rejected"]) == n and saved["status"] == "done", st.msg


def test_real_predictor_contract(proj):
    """racklay.predict.Predictor (a tiny random model) plugs into the tool."""
    torch = pytest.importorskip("torch")
    from racklay.model import ModelConfig, RackLayNet
    from racklay.predict import Predictor

    torch.manual_seed(0)
    cfg = ModelConfig(R=4, image_size=64, layout_size=64, decoder="light")
    predictor = Predictor.from_model(RackLayNet(cfg).eval(), cfg)
    tool = Tool(proj, predictor=predictor)
    st = label_by_clicks(tool, tool.open("r.png"), dict(clicks(CAM), boxes=[]))
    assert isinstance(st.ann["proposals"], list)
    assert "⚠" not in st.msg


def test_build_app_smoke(proj):
    demo = build_app(proj)
    assert demo.tool.project is proj


def test_missing_browser_fails_in_ci_and_skips_elsewhere(monkeypatch):
    import annotate.browser as B

    monkeypatch.setattr(B, "CHROMIUM", "/nonexistent/chromium")
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="chromium"):
        B.require_browser()
    monkeypatch.setenv("CI", "")
    with pytest.raises(pytest.skip.Exception, match="chromium"):
        B.require_browser()


def test_rack_size_and_preset(proj):
    tool = Tool(proj)
    st = tool.click(tool.open("r.png"), 10, 10)  # first corner applies the default preset
    assert st.ann["rack"]["preset"] == proj.settings["default_preset"]
    v = st.ann["version"]
    st = tool.set_rack(st, width=st.ann["rack"]["width"])  # unchanged value (a blur): no save
    assert st.ann["version"] == v and st.ann["rack"]["preset"]
    st = tool.set_rack(st, depth=0.45)
    assert proj.load("r.png")["rack"]["depth"] == 0.45 and proj.load("r.png")["rack"]["preset"] is None
    st = tool.set_rack(st, width=-1)
    assert "⚠" in st.msg and proj.load("r.png")["rack"]["width"] > 0
    st = tool.set_rack(st, preset_name="longspan 2.4 × 2.4 × 0.8 m")
    assert proj.load("r.png")["rack"]["depth"] == 0.8


@pytest.mark.parametrize("port", ["99999", "-1", "0", "http"])
def test_serve_port_out_of_range_refused(proj, port, capsys):
    from annotate.cli import main as annotate_main

    with pytest.raises(SystemExit) as e:
        annotate_main(["serve", str(proj.root), "--port", port])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "argument --port" in err and "not a port number (1-65535)" in err
    assert "Traceback" not in err



def test_serve_gap_cut_flags_reach_the_tool_and_bad_values_are_refused(proj, monkeypatch, capsys):
    """`--gap-depth 0` (no cut at the photo's gaps) and `--gap-width` reach the served tool's
    GapSplit; a negative depth is refused by argparse with one line naming the flag."""
    import annotate.server as A
    from annotate.cli import main as annotate_main

    got = {}
    monkeypatch.setattr(A, "serve", lambda *a, **kw: got.update(kw))
    assert annotate_main(["serve", str(proj.root), "--no-model", "--gap-depth", "0", "--gap-width", "0.25"]) == 0
    assert got["gap_split"] == G.GapSplit(depth=0.0, close_m=0.25)
    assert annotate_main(["serve", str(proj.root), "--no-model"]) == 0
    assert got["gap_split"] == G.GapSplit()
    with pytest.raises(SystemExit) as e:
        annotate_main(["serve", str(proj.root), "--gap-depth", "-1"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "argument --gap-depth: must be >= 0, got -1" in err


def test_serve_runs_the_model_at_the_precision_asked(proj, monkeypatch, tmp_path):
    """`annotate serve` takes `--precision` as `racklay predict` does (default auto: bf16 where
    the CPU has it) and its pre-labelling model runs at that precision."""
    import annotate.server as A
    from annotate.cli import main as annotate_main
    from racklay.checkpoint import save_checkpoint
    from racklay.model import ModelConfig, RackLayNet

    got = {}
    monkeypatch.setattr(A, "serve", lambda *a, **kw: got.update(kw))
    assert annotate_main(["serve", str(proj.root), "--no-model"]) == 0
    assert got["precision"] == "auto"
    assert annotate_main(["serve", str(proj.root), "--no-model", "--fp32"]) == 0
    assert got["precision"] == "fp32"
    cfg = ModelConfig(R=2, image_size=(64, 128), layout_size=32)
    ckpt = tmp_path / "m.safetensors"
    save_checkpoint(ckpt, RackLayNet(cfg).eval(), cfg)
    assert A.load_predictor(str(ckpt), precision="bf16").precision == "bf16"
    assert A.load_predictor(str(ckpt), backend="onnx", precision="auto").precision == "fp32"


@pytest.mark.parametrize("checked", [True, False])
def test_serve_busy_port_one_line(proj, monkeypatch, capsys, checked):
    """A busy port is refused before the app is built, and gradio's own port error (the race
    after the check) is turned into the same one line."""
    import socket

    import annotate.server as A
    from annotate.cli import main as annotate_main

    if not checked:
        monkeypatch.setattr(A, "check_port", lambda host, port: None)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        rc = annotate_main(["serve", str(proj.root), "--port", str(port)])
    out, err = capsys.readouterr()
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"cannot serve on 127.0.0.1:{port}" in err and "choose another --port" in err
    assert "serving" not in out


@pytest.mark.slow
def test_serve_temp_folder_removed_after_sigterm(proj, tmp_path):
    """Everything a server run puts in the temp folder (gradio's cache, uploads, rendered photos)
    lives in one folder that is gone after SIGTERM. The server runs with --auth-file: gradio's
    login takes the file's users and refuses a wrong password."""
    import signal
    import socket
    import subprocess
    import sys
    import urllib.error
    import urllib.parse
    import urllib.request

    from annotate.auth import set_password

    logins = tmp_path / "logins"
    set_password(logins, "ana", "correct horse")

    def login(user, pw):
        data = urllib.parse.urlencode({"username": user, "password": pw}).encode()
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/login", data=data, timeout=60) as r:
                return r.status
        except urllib.error.HTTPError as e:
            return e.code

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "TMPDIR": str(tmp), "GRADIO_ANALYTICS_ENABLED": "False"}
    env.pop("GRADIO_TEMP_DIR", None)
    p = subprocess.Popen([sys.executable, "-m", "annotate.cli", "serve", str(proj.root), "--port", str(port),
                          "--auth-file", str(logins)],
                         env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        line = p.stdout.readline()          # "annotate: serving ..." once the server listens
        assert "serving" in line, line + p.stdout.read() if p.poll() is not None else line
        run_dirs = [d.name for d in tmp.iterdir()]
        assert len(run_dirs) == 1 and run_dirs[0].startswith("annotate-run-"), run_dirs
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=60) as r:
            assert r.status == 200
        assert login("ana", "wrong horse") == 400 and login("ana", "correct horse") == 200
        p.send_signal(signal.SIGTERM)
        p.wait(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 128 + signal.SIGTERM
    assert list(tmp.iterdir()) == []


def test_done_refused_while_warnings_or_unconfirmed_preset(proj):
    """`done` is refused (one line saying what to fix) while the rack size is the default preset
    nobody confirmed, or the geometry warns; the work itself is saved all along."""
    tool = Tool(proj)
    st = label_by_clicks(tool, tool.open("r.png"), clicks(CAM))   # the first corner applied the default preset
    st = tool.set_status(st, "done")
    assert st.msg.startswith("⚠ not marked done: the rack size 2 × 2 × 0.6 m is the default preset, not confirmed")
    assert "\n" not in st.msg
    saved = proj.load("r.png")
    assert saved["status"] == "in progress" and len(saved["boxes"]) == len(BOXES)   # work in progress kept
    st = tool.confirm_size(st)
    st = tool.add_box(st, *CAM.project([[0.3, 0, 0.02], [0.6, 0, 0.08]]).tolist())   # below every shelf: a warning
    st = tool.set_status(st, "done")
    assert "not marked done: box" in st.msg and "below every marked shelf" in st.msg
    assert proj.load("r.png")["status"] == "in progress"
    st = tool.delete(st)                           # the new box is selected: delete it
    st = tool.set_status(st, "done")
    assert proj.load("r.png")["status"] == "done", st.msg


def test_reload_reopens_last_photo_with_undo_history(proj):
    """A new server process (or a reloaded page) opens the photo the labeller had open last,
    even when it is done, and its undo history still works."""
    (proj.root / "s.png").write_bytes(encode_png(np.full((480, 640, 3), 90, np.uint8)))
    tool = Tool(proj)
    st = tool.open("s.png")
    st = tool.click(st, 10, 10)
    st = tool.click(st, 600, 12)
    tool.flush_history()
    again = Tool(Project(proj.root))
    st2 = again.open(again.project.resume_image())
    assert st2.name == "s.png" and len(st2.undo) == 2
    st2 = again.undo(st2)
    assert proj.load("s.png")["rack"]["corners"] == [[10, 10]]
    st2 = again.undo(st2, redo=True)
    assert len(proj.load("s.png")["rack"]["corners"]) == 2
    again.flush_history()
    # the file was saved by other means meanwhile: the history no longer fits, it is not offered
    ann = proj.load("s.png")
    ann["rack"]["corners"].append([300, 400])
    proj.save(ann)
    assert Tool(Project(proj.root)).open("s.png").undo == []


def test_photo_list_filter_and_next_unfinished(proj):
    for n in ("s.png", "t.png"):
        (proj.root / n).write_bytes(encode_png(np.full((480, 640, 3), 90, np.uint8)))
    (proj.root / "u.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")   # unreadable: listed, skipped
    ann = proj.load("s.png")
    ann["status"] = "done"
    proj.save(ann)
    tool = Tool(proj)
    assert proj.statuses() == {"r.png": "todo", "s.png": "done", "t.png": "todo", "u.png": "unreadable"}
    st = tool.open("r.png")
    st = tool.apply(st, [{"seq": 1, "kind": "filter", "value": "unfinished"}])
    assert tool.listed(st) == ["r.png", "t.png"]
    st = tool.apply(st, [{"seq": 2, "kind": "act", "name": "next_unfinished"}])
    assert st.name == "t.png"
    st = tool.step(st, +1, unfinished=True)
    assert st.name == "r.png"               # s.png is done, u.png unreadable
    st = tool.apply(st, [{"seq": 3, "kind": "filter", "value": "all"}, {"seq": 4, "kind": "act", "name": "prev"}])
    assert st.name == "t.png" and st.ack == 4   # u.png skipped
    bad = tool.open("u.png")
    assert bad.ann is None and "u.png" in bad.msg and "\n" not in bad.msg


def test_actions_applied_once_in_order_and_bad_ones_refused(proj):
    """The page's batches: each action applied once, in order (a batch sent again is not applied
    twice); a point outside the photo is refused by the server with one line and not saved."""
    tool = Tool(proj)
    st = tool.open("r.png")
    batch = [{"seq": 1, "kind": "click", "x": 10, "y": 10, "image": "r.png"},
             {"seq": 2, "kind": "click", "x": 600, "y": 12, "image": "r.png"}]
    st = tool.apply(st, batch)
    st = tool.apply(st, batch)                  # the answer was lost; the page asks again
    assert proj.load("r.png")["rack"]["corners"] == [[10, 10], [600, 12]]
    v = proj.load("r.png")["version"]
    st = tool.apply(st, [{"seq": 3, "kind": "click", "x": 1e9, "y": 5, "image": "r.png"}])
    assert st.msg.startswith("⚠ not saved: ") and "outside the 640x480 photo" in st.msg and "\n" not in st.msg
    st = tool.apply(st, [{"seq": 4, "kind": "click", "x": float("nan"), "y": 5}, {"seq": 5, "kind": "warp"}])
    assert "malformed" in st.msg and proj.load("r.png")["version"] == v
    st = tool.apply(st, [{"seq": 6, "kind": "click", "x": 5, "y": 5, "image": "other.png"}])
    assert "not applied" in st.msg and proj.load("r.png")["version"] == v


def test_typed_field_text_stored_exactly(proj):
    tool = Tool(proj)
    st = tool.click(tool.open("r.png"), 10, 10)
    for f, text, want in (("width", "0.74", 0.74), ("height", "1.83", 1.83), ("depth", " 0.39 ", 0.39)):
        st = tool.apply(st, [{"seq": st.ack + 1, "kind": "field", "field": f, "text": text}])
        assert proj.load("r.png")["rack"][f] == want
    st = tool.apply(st, [{"seq": st.ack + 1, "kind": "field", "field": "width", "text": "2,74"}])
    assert "not a number" in st.msg and proj.load("r.png")["rack"]["width"] == 0.74
    assert proj.load("r.png")["rack"]["size_confirmed"] is True


def test_box_depth_and_offset_by_clicking(proj):
    """Mode 7: a click on the selected box's top-back edge sets its depth; mode 8: a click on the
    board where its front stands sets its front offset (camera from the rack plane)."""
    tool = Tool(proj)
    truth = clicks(CAM)
    st = label_by_clicks(tool, tool.open("r.png"), dict(truth, boxes=[]))
    st = tool.set_rack(st, depth=0.6)
    s, x0, x1, z0, z1, o, d = 1, 0.20, 0.90, 0.0, 0.50, 0.0, 0.50   # BOXES[3]
    zb = BOARDS[s]
    p = CAM.project([[x0, o, zb + z0], [x1, o, zb + z1]])
    st.mode = "boxes"
    st = tool.click(st, *p[0])
    st = tool.click(st, *p[1])
    st = tool.apply(st, [{"seq": 1, "kind": "mode", "mode": "depth"}])
    st = tool.click(st, *CAM.project([[(x0 + x1) / 2, o + d, zb + z1]])[0])
    box = proj.load("r.png")["boxes"][0]
    assert box["depth"] == pytest.approx(d, abs=0.02) and st.mode == "boxes"
    st = tool.apply(st, [{"seq": 2, "kind": "mode", "mode": "offset"}])
    st = tool.click(st, *CAM.project([[x0 + 0.1, 0.07, zb]])[0])
    assert proj.load("r.png")["boxes"][0]["front_offset"] == pytest.approx(0.07, abs=0.01)


def test_squeezed_photos_pixel_aspect_depth_clicks_model_and_export(tmp_path):
    """A project of photos stored squeezed to half their width (pixel aspect 2, `serve
    --pixel-aspect 2:1`): the depth click still measures the box's depth (the camera has square
    pixels as taken), the model is shown the photo as taken, and export writes it so."""
    from annotate.commands.serve import pixel_aspect_value
    from annotate.dataset import export_project
    from racklay.data import RackLayRoot

    (tmp_path / "r.png").write_bytes(encode_png(np.full((480, 320, 3), 90, np.uint8)))
    squeeze = np.diag([0.5, 1.0])

    def sq(p):
        return (np.asarray(p, float) @ squeeze).tolist()
    truth = clicks(CAM)
    ann = dict(truth, boxes=[], image_size=[320, 480])
    ann["rack"] = dict(ann["rack"], corners=sq(ann["rack"]["corners"]))
    ann["shelves"] = [dict(x, point=sq([x["point"]])[0]) for x in ann["shelves"]]
    s_, x0, x1, z0, z1, o, d = 1, 0.20, 0.90, 0.0, 0.50, 0.0, 0.50   # BOXES[3]
    zb = BOARDS[s_]
    depth = {}
    for aspect in (1.0, pixel_aspect_value("2:1")):
        proj = Project(tmp_path / f"a{aspect:g}")
        proj.add_image("r.png", (tmp_path / "r.png").read_bytes())
        proj.save_settings(dict(proj.settings, D=256, extent=4.0, pixel_aspect=aspect))
        pred = StandIn()
        tool = Tool(proj, predictor=pred)
        st = label_by_clicks(tool, tool.open("r.png"), ann)
        st = tool.set_rack(st, depth=0.6)
        st.mode = "boxes"
        p = sq(CAM.project([[x0, o, zb + z0], [x1, o, zb + z1]]))
        st = tool.drag(st, p[0], p[1])
        st = tool.apply(st, [{"seq": 1, "kind": "mode", "mode": "depth"}])
        st = tool.click(st, *sq(CAM.project([[(x0 + x1) / 2, o + d, zb + z1]]))[0])
        depth[aspect] = proj.load("r.png")["boxes"][0]["depth"]
        assert pred.shapes == [(480, round(320 * aspect), 3)]
        # the model reads the rack the labeller outlined, in the photo as taken
        c = np.asarray(ann["rack"]["corners"]) * [aspect, 1.0]
        np.testing.assert_allclose(pred.boxes, [[*c.min(0), *c.max(0)]], atol=0.1)
    import argparse
    for bad, why in (("wide", "not a pixel aspect"), ("16:0", "not a pixel aspect"), ("9", "outside")):
        with pytest.raises(argparse.ArgumentTypeError, match=why):
            pixel_aspect_value(bad)
    assert depth[2.0] == pytest.approx(d, abs=0.02)
    assert abs(depth[1.0] - d) > 0.05        # taken as square pixels, the same click is wrong
    st = tool.confirm_size(st)
    st = tool.mark_done(st)
    st = tool.mark_done(st, "reject_proposals")
    assert proj.load("r.png")["status"] == "done", st.msg
    export_project(proj, tmp_path / "ds", fractions={"test": 1.0})
    ds = RackLayRoot(tmp_path / "ds")
    sid = ds.split_ids("test")[0]
    assert ds.read_image(sid).shape == (480, 640, 3)          # as taken


def test_scene_built_at_most_once_per_event(proj, monkeypatch):
    """An event from the page (a batch of actions through the app's handler, the answer drawn,
    then the preview) builds the annotation's scene at most once, and not at all when the rack,
    shelves and boxes did not change (a mode key, a selection, a status); it was 1-4 times."""
    import json
    from types import SimpleNamespace

    real, calls = G.build_scene, []
    monkeypatch.setattr(G, "build_scene", lambda *a, **k: calls.append(1) or real(*a, **k))
    demo = build_app(proj)
    fns = {f.name: f.fn for f in demo.fns.values()}
    req = SimpleNamespace(username=None)
    st = fns["on_load"](req)[0]
    seq = 0

    def builds(*actions):
        nonlocal st, seq
        calls.clear()
        batch = []
        for a in actions:
            seq += 1
            batch.append(dict(a, seq=seq))
        st = fns["on_actions"](st, json.dumps(batch), req)[0]
        fns["on_preview"](st)
        return len(calls)

    truth = clicks(CAM)
    click = [{"kind": "click", "x": x, "y": y, "image": "r.png"} for x, y in
             truth["rack"]["corners"] + [s["point"] for s in truth["shelves"]]]
    assert [builds(c) for c in click] == [1] * len(click)   # every click changes the geometry
    b = truth["boxes"][0]
    assert builds({"kind": "mode", "mode": "boxes"}) == 0
    assert builds({"kind": "click", "x": b["p0"][0], "y": b["p0"][1], "image": "r.png"}) == 0  # half a box
    assert builds({"kind": "click", "x": b["p1"][0], "y": b["p1"][1], "image": "r.png"}) == 1
    centre = [(b["p0"][0] + b["p1"][0]) / 2, (b["p0"][1] + b["p1"][1]) / 2]
    assert builds({"kind": "mode", "mode": "select"}, {"kind": "click", "x": centre[0], "y": centre[1]}) == 0
    assert st.sel == ["box", 0]
    assert builds({"kind": "mode", "mode": "move"}, {"kind": "click", "x": centre[0] + 5, "y": centre[1]}) == 1
    assert builds({"kind": "status", "value": "needs review"}) == 0
    assert builds({"kind": "act", "name": "undo"}) == 0        # back to a geometry seen a moment ago
    assert proj.load("r.png")["status"] == "in progress" and len(proj.load("r.png")["boxes"]) == 1


def test_a_photo_deleted_while_open_is_not_annotated(proj):
    """The photo is removed while a labeller has it open: the next edit is refused with one line
    saying so (it used to save an annotation for the missing photo, then fail with '[Errno 2] ...')."""
    tool = Tool(proj)
    st = tool.open("r.png")
    (proj.root / "r.png").unlink()
    st = tool.click(st, 100.0, 100.0)
    assert st.msg.startswith("⚠ not saved: r.png: the photo is no longer in the project")
    assert not proj.annotation_path("r.png").exists()


def test_a_squeezed_photos_gaps_are_read_where_the_rack_is(tmp_path):
    """In a project of squeezed photos (`serve --pixel-aspect 2:1`) the rack plane lives in the
    stored pixels: `W` reads the photo's slots there and cuts the row where an unsqueezed photo of
    the same rack is cut."""
    import cv2

    from annotate.commands.serve import pixel_aspect_value

    truth = clicks(CAM)
    s_, x0, x1, top = 2, 0.50, 1.50, 0.45
    rgb = cv2.imdecode(np.frombuffer(slot_photo(G.build_scene(truth, Project(tmp_path / "p0").settings).plane,
                                                [(0.78, 0.82), (1.10, 1.16)], BOARDS[s_], BOARDS[s_] + top),
                                     np.uint8), cv2.IMREAD_COLOR)
    (tmp_path / "sq.png").write_bytes(encode_png(cv2.resize(rgb, (320, 480), interpolation=cv2.INTER_AREA)))

    def sq(p):
        return (np.asarray(p, float) * [0.5, 1.0]).tolist()
    ann = dict(truth, image="sq.png", boxes=[], image_size=[320, 480])
    ann["rack"] = dict(ann["rack"], corners=sq(ann["rack"]["corners"]))
    ann["shelves"] = [dict(x, point=sq([x["point"]])[0]) for x in ann["shelves"]]
    proj = Project(tmp_path / "p")
    proj.add_image("sq.png", (tmp_path / "sq.png").read_bytes())
    proj.save_settings(dict(proj.settings, pixel_aspect=pixel_aspect_value("2:1")))
    tool = Tool(proj)
    st = label_by_clicks(tool, tool.open("sq.png"), ann)
    p = sq(CAM.project([[x0, 0.0, BOARDS[s_]], [x1, 0.0, BOARDS[s_] + top]]))
    st.mode = "boxes"
    st = tool.drag(st, p[0], p[1])
    st = tool.apply(st, [{"kind": "act", "name": "split_at_gaps", "seq": 1}])
    spans = sorted((m.u0, m.u1) for m in G.build_scene(proj.load("sq.png"), proj.settings).boxes)
    np.testing.assert_allclose(spans, [[0.50, 0.78], [0.82, 1.10], [1.16, 1.50]], atol=0.02), st.msg
