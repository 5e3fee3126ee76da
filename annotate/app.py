"""The annotation tool in the browser (gradio 6).

The labeller clicks the rack's four corners, one point on each shelf board's front edge and two
opposite corners of each box's front face; annotate.geometry turns the clicks into metric
shelves and boxes, racklay.layout draws every shelf's top and front layout live beside the
photo, and the metric boxes are projected back onto the photo as outlines. Every action is saved
at once through annotate.store (atomic, version-checked); this module never touches the files.

Offline by design: analytics off, a built-in theme with system fonts, no CDN assets.
"""


import contextlib
import copy
import os
import threading
from collections import OrderedDict

os.environ.setdefault("GRADIO_ANALYTICS_ENABLED", "False")

import numpy as np

from racklay import layout as L
from racklay.viz import PALETTE, colorize, content_window

from . import geometry as G
from . import schema as S
from .dataset import read_imported
from .store import ConflictError, Project, StoreError

DISPLAY_W, DISPLAY_H = 960, 640  # the photo viewer, in CSS pixels
MODES = ("corners", "shelves", "boxes", "select", "move", "resize")
MODE_HELP = {
    "corners": "click the 4 corners of the rack's front face (any order); a 5th click moves the nearest corner",
    "shelves": "click once on each shelf board's front edge",
    "boxes": "click two opposite corners of a box's (or stack's) front face",
    "select": "click a corner, shelf line, box or proposal to select it",
    "move": "click where the selected item should go (a box moves its centre there)",
    "resize": "click where the nearest corner of the selected box should go",
}
#: key -> button elem_id (the keydown script in HEAD clicks the button)
SHORTCUTS = [
    ("1 … 6", "mode: corners, shelves, boxes, select, move, resize", None),
    ("n / →", "next image", "btn-next"), ("p / ←", "previous image", "btn-prev"),
    ("z / Ctrl+Z", "undo", "btn-undo"), ("y / Ctrl+Y", "redo", "btn-redo"),
    ("Del / Backspace / x", "delete selected (a proposal: reject)", "btn-delete"),
    ("s / Ctrl+S", "save now", "btn-save"), ("d", "mark done", "btn-done"),
    ("a / r", "accept / reject selected proposal", None), ("A", "accept all proposals", "btn-accept-all"),
    ("+ / - / 0", "zoom in / out / reset (centred on the last click)", None),
    ("Esc", "cancel a half-drawn box", "btn-cancel"),
]
KEYMAP = {
    "1": "mode-corners", "2": "mode-shelves", "3": "mode-boxes", "4": "mode-select", "5": "mode-move",
    "6": "mode-resize", "n": "btn-next", "ArrowRight": "btn-next", "p": "btn-prev", "ArrowLeft": "btn-prev",
    "z": "btn-undo", "Ctrl+z": "btn-undo", "y": "btn-redo", "Ctrl+y": "btn-redo", "Ctrl+Z": "btn-redo",
    "Delete": "btn-delete", "Backspace": "btn-delete", "x": "btn-delete", "s": "btn-save", "Ctrl+s": "btn-save",
    "d": "btn-done", "a": "btn-accept", "r": "btn-reject", "A": "btn-accept-all", "+": "btn-zoom-in",
    "=": "btn-zoom-in", "-": "btn-zoom-out", "0": "btn-zoom-reset", "Escape": "btn-cancel",
}


def _head() -> str:
    import json

    return """<script>
(() => {
  const KEYMAP = %s;
  document.addEventListener('keydown', (e) => {
    const t = e.target, tag = ((t && t.tagName) || '').toLowerCase();
    if (tag === 'input' || tag === 'textarea' || tag === 'select' || (t && t.isContentEditable)) return;
    if (e.altKey) return;
    const key = (e.ctrlKey || e.metaKey) ? 'Ctrl+' + e.key : e.key;
    const id = KEYMAP[key];
    if (!id) return;
    const el = document.getElementById(id);
    if (!el) return;
    e.preventDefault();
    (el.tagName === 'BUTTON' ? el : (el.querySelector('button') || el)).click();
  });
})();
</script>""" % json.dumps(KEYMAP)


CSS = """
#photo img { cursor: crosshair; }
#header { font-size: 1.05em; }
.mode-row button { min-width: 0; }
"""

# overlay colours (RGB)
C_RACK, C_SHELF, C_BOX, C_FLOAT = (255, 220, 0), (0, 220, 255), tuple(int(v) for v in PALETTE[L.BOX]), (255, 60, 60)
C_PROP, C_SEL, C_PEND, C_IMPORT = (60, 240, 90), (255, 255, 255), (255, 0, 255), (190, 120, 255)


class Tool:
    """Server-side logic, independent of gradio: each method takes and returns the session state
    (a plain dict) so it can be tested without a browser."""

    #: rendered photos kept on disk: gradio copies each into its cache as the handler returns, so
    #: only the newest few are still needed (the copies go with delete_cache and at exit)
    KEEP_SHOTS = 4

    def __init__(self, project: Project, predictor=None, user: str | None = None, tmp_dir: str | None = None):
        self.project = project
        self.predictor = predictor
        self.user = user
        self._images: OrderedDict[str, np.ndarray] = OrderedDict()
        self._preds: OrderedDict[str, dict] = OrderedDict()
        self._lock = threading.RLock()
        self._tmp_root = tmp_dir   # the server run's temp folder (None: the system's)
        self._tmp = None
        self._shots: list[str] = []
        self._n_shots = 0

    def photo_file(self, st: dict) -> str | None:
        """The rendered photo as a JPEG file for the viewer (4:4:4 chroma, quality 92, so thin
        coloured outlines stay sharp). Encoding it as PNG took 670 ms per click for a 1280x1006
        photo (gradio's PIL encoder) against ~15 ms here; the layouts preview stays PNG."""
        import cv2
        import tempfile

        img = self.render_photo(st)
        if img is None:
            return None
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img[:, :, ::-1]),
                               [cv2.IMWRITE_JPEG_QUALITY, 92, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                                cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
        with self._lock:
            if self._tmp is None:
                self._tmp = tempfile.mkdtemp(prefix="annotate-view-", dir=self._tmp_root)
            self._n_shots += 1
            path = os.path.join(self._tmp, f"view-{self._n_shots}.jpg")
            with open(path, "wb") as f:
                f.write(buf.tobytes())
            self._shots.append(path)
            while len(self._shots) > self.KEEP_SHOTS:  # gradio has copied older ones into its cache by now
                try:
                    os.unlink(self._shots.pop(0))
                except OSError:
                    pass
        return path

    # --- state ---------------------------------------------------------------------------
    def open(self, name: str | None, user: str | None = None) -> dict:
        """A session state for image `name`; `user` is the logged-in user (saves record it)."""
        st = {"name": name, "ann": None, "undo": [], "redo": [], "pending": None, "sel": None,
              "mode": "corners", "zoom": 1.0, "center": None, "msg": "", "error": None, "user": user}
        if name is None:
            st["msg"] = "no images in the project yet: upload some"
            return st
        try:
            ann = self.project.load(name)
        except (S.SchemaError, StoreError) as e:
            st["error"] = str(e)
            st["msg"] = f"⚠ {e} — this file is not overwritten; fix or delete it by hand"
            return st
        st["ann"] = ann
        rack = ann["rack"]
        st["mode"] = "corners" if len(rack["corners"]) < 4 else ("shelves" if not ann["shelves"] else "boxes")
        st["msg"] = f"opened {name} (version {ann['version']}, {ann['status']})"
        return st

    def image(self, name: str) -> np.ndarray:
        with self._lock:
            if name not in self._images:
                self._images[name] = self.project.read_image(name)
                while len(self._images) > 8:
                    self._images.popitem(last=False)
            self._images.move_to_end(name)
            return self._images[name]

    def step(self, st: dict, delta: int) -> dict:
        names = self.project.images()
        if not names:
            return self.open(None, st.get("user"))
        i = names.index(st["name"]) if st.get("name") in names else -1
        return self.open(names[(i + delta) % len(names)], st.get("user"))

    # --- applying an edit: save at once, with undo ----------------------------------------
    def act(self, st: dict, fn) -> dict:
        if st.get("ann") is None:
            st["msg"] = st.get("msg") or "nothing to edit"
            return st
        before = st["ann"]
        ann = copy.deepcopy(before)
        msg = fn(ann)
        if _content(ann) == _content(before):
            st["msg"] = msg or st.get("msg", "")
            return st
        if ann["status"] == before["status"] == "todo":
            ann["status"] = "in progress"
        if self.predictor is not None and (ann["rack"] != before["rack"] or ann["shelves"] != before["shelves"]):
            pm = self.refresh_proposals(ann)
            msg = f"{msg}; {pm}" if msg and pm else (msg or pm)
        if self._save(st, ann):
            st["undo"].append(before)
            st["undo"] = st["undo"][-200:]
            st["redo"] = []
            st["msg"] = msg or f"saved (version {st['ann']['version']})"
        return st

    def _save(self, st: dict, ann: dict) -> bool:
        try:
            st["ann"] = self.project.save(ann, user=st.get("user") or self.user)
            return True
        except ConflictError as e:
            st["msg"] = f"⚠ {e}"
        except (S.SchemaError, StoreError) as e:
            st["msg"] = f"⚠ not saved: {e}"
        return False

    def undo(self, st: dict, redo: bool = False) -> dict:
        src, dst = ("redo", "undo") if redo else ("undo", "redo")
        if st.get("ann") is None or not st[src]:
            st["msg"] = f"nothing to {'redo' if redo else 'undo'}"
            return st
        target = copy.deepcopy(st[src][-1])
        current = st["ann"]
        target["version"] = current["version"]
        if self._save(st, target):
            st[src].pop()
            st[dst].append(current)
            st["sel"], st["pending"] = None, None
            st["msg"] = f"{'redone' if redo else 'undone'} (version {st['ann']['version']})"
        return st

    def save_now(self, st: dict) -> dict:
        if st.get("ann") is None:
            return st
        if self._save(st, copy.deepcopy(st["ann"])):
            st["msg"] = f"saved (version {st['ann']['version']})"
        return st

    # --- clicks ----------------------------------------------------------------------------
    def display_to_image(self, st: dict, x: float, y: float) -> tuple[float, float]:
        x0, y0, s = self.view(st)
        return x0 + (x + 0.5) / s - 0.5, y0 + (y + 0.5) / s - 0.5

    def view(self, st: dict) -> tuple[float, float, float]:
        """(x0, y0, scale): the displayed window's top-left in image pixels, and display pixels
        per image pixel. Small photos are enlarged to fill the viewer (DISPLAY_W x DISPLAY_H);
        zoom crops a window around the last click."""
        if st.get("ann") is None:
            return 0.0, 0.0, 1.0
        W, H = st["ann"]["image_size"]
        base = max(1.0, round(min(DISPLAY_W / W, DISPLAY_H / H), 3))
        z = max(1.0, float(st.get("zoom") or 1.0))
        if z == 1:
            return 0.0, 0.0, base
        cx, cy = st.get("center") or (W / 2, H / 2)
        w, h = W / z, H / z
        return float(int(np.clip(cx - w / 2, 0, W - w))), float(int(np.clip(cy - h / 2, 0, H - h))), base * z

    def click(self, st: dict, x: float, y: float) -> dict:
        """A click at display pixel (x, y) in the current mode."""
        if st.get("ann") is None:
            return st
        x, y = self.display_to_image(st, x, y)
        pt = [round(float(x), 2), round(float(y), 2)]
        st["center"] = pt
        mode = st["mode"]
        if mode == "corners":
            return self.act(st, lambda a: self._corner(st, a, pt))
        if mode == "shelves":
            def add_shelf(a):
                a["shelves"].append({"id": _next_id(a["shelves"]), "point": pt})
                return f"shelf {len(a['shelves'])} marked"
            return self.act(st, add_shelf)
        if mode == "boxes":
            if st.get("pending") is None:
                st["pending"] = pt
                st["msg"] = "now click the opposite corner of the box's front face"
                return st
            p0, st["pending"] = st["pending"], None

            def add_box(a):
                b = {"id": _next_id(a["boxes"]), "p0": p0, "p1": pt, "source": "manual"}
                a["boxes"].append(b)
                st["sel"] = ["box", b["id"]]
                return f"box {b['id']} added"
            return self.act(st, add_box)
        if mode == "select":
            st["sel"] = self.pick(st, pt)
            st["msg"] = f"selected {st['sel'][0]} {st['sel'][1]}" if st["sel"] else "nothing here"
            return st
        if mode in ("move", "resize"):
            if not st.get("sel"):
                st["msg"] = "select something first (mode 4)"
                return st
            return self.act(st, lambda a: self._move(st, a, pt, resize=mode == "resize"))
        return st

    def _corner(self, st, a, pt):
        c = a["rack"]["corners"]
        if a["rack"]["width"] is None:
            p = S.preset(self.project.settings, self.project.settings.get("default_preset"))
            if p:
                a["rack"].update(width=p["width"], height=p["height"], depth=p["depth"], preset=p["name"])
        if len(c) < 4:
            c.append(pt)
            if len(c) == 4:
                st["mode"] = "shelves"
                return "4 corners set: now click each shelf board's front edge"
            return f"corner {len(c)} of 4"
        k = int(np.argmin([np.hypot(q[0] - pt[0], q[1] - pt[1]) for q in c]))
        c[k] = pt
        return f"corner {k + 1} moved"

    def _move(self, st, a, pt, resize=False):
        kind, key = st["sel"]
        if kind == "corner" and key < len(a["rack"]["corners"]):
            a["rack"]["corners"][key] = pt
            return f"corner {key + 1} moved"
        if kind == "shelf":
            for s in a["shelves"]:
                if s["id"] == key:
                    s["point"] = pt
                    return f"shelf moved"
        if kind in ("box", "proposal"):
            items = a["boxes"] if kind == "box" else a["proposals"]
            for b in items:
                if b["id"] == key:
                    if resize:
                        for ax in (0, 1):
                            k = "p0" if abs(b["p0"][ax] - pt[ax]) <= abs(b["p1"][ax] - pt[ax]) else "p1"
                            b[k] = list(b[k])
                            b[k][ax] = pt[ax]
                        return f"{kind} {key} resized"
                    dx = pt[0] - (b["p0"][0] + b["p1"][0]) / 2
                    dy = pt[1] - (b["p0"][1] + b["p1"][1]) / 2
                    b["p0"] = [round(b["p0"][0] + dx, 2), round(b["p0"][1] + dy, 2)]
                    b["p1"] = [round(b["p1"][0] + dx, 2), round(b["p1"][1] + dy, 2)]
                    return f"{kind} {key} moved"
        return "the selected item is gone"

    def pick(self, st: dict, pt) -> list | None:
        """The item under a click: a corner, then the smallest box or proposal containing it,
        then the nearest shelf line."""
        a = st["ann"]
        W, H = a["image_size"]
        tol = max(W, H) / 50 / max(1.0, float(st.get("zoom") or 1.0))
        for k, q in enumerate(a["rack"]["corners"]):
            if np.hypot(q[0] - pt[0], q[1] - pt[1]) <= tol:
                return ["corner", k]
        scene = self._scene(a)
        best = None
        for kind, items in (("box", a["boxes"]), ("proposal", a.get("proposals", []))):
            for b in items:
                poly = self._box_poly(scene, b)
                if _inside(poly, pt):
                    area = abs(_poly_area(poly))
                    if best is None or area < best[0]:
                        best = (area, [kind, b["id"]])
        if best:
            return best[1]
        if scene is not None:
            for sid, v in zip(scene.shelf_ids, scene.shelf_v):
                seg = G.shelf_line(scene.plane, v)
                if _seg_dist(seg, pt) <= tol:
                    return ["shelf", sid]
        return None

    def delete(self, st: dict) -> dict:
        sel = st.get("sel")
        if not sel:
            st["msg"] = "nothing selected"
            return st
        if sel[0] == "proposal":
            return self.reject(st)
        kind, key = sel

        def rm(a):
            if kind == "corner":
                if key < len(a["rack"]["corners"]):
                    a["rack"]["corners"].pop(key)
            elif kind == "shelf":
                a["shelves"] = [s for s in a["shelves"] if s["id"] != key]
            elif kind == "box":
                a["boxes"] = [b for b in a["boxes"] if b["id"] != key]
            return f"{kind} {key} deleted"
        st["sel"] = None
        if kind == "corner":
            st["mode"] = "corners"
        return self.act(st, rm)

    def set_box_field(self, st: dict, field: str, value) -> dict:
        sel = st.get("sel")
        if not sel or sel[0] not in ("box", "proposal"):
            if value is not None:
                st["msg"] = "select a box first"
            return st
        if value is not None and (not np.isfinite(value) or value < 0 or (field == "depth" and value == 0)):
            st["msg"] = f"⚠ {field.replace('_', ' ')} must be a positive number of metres"
            return st

        def upd(a):
            for b in a["boxes"] if sel[0] == "box" else a["proposals"]:
                if b["id"] == sel[1]:
                    if value is None:
                        b.pop(field, None)
                    else:
                        b[field] = round(float(value), 4)
                    return f"{sel[0]} {sel[1]}: {field.replace('_', ' ')} {value} m"
        return self.act(st, upd)

    def set_rack(self, st: dict, preset_name=None, width=None, height=None, depth=None) -> dict:
        def upd(a):
            r = a["rack"]
            before_rack = dict(r)
            if preset_name is not None:
                p = S.preset(self.project.settings, preset_name)
                if p is None:
                    return f"unknown preset {preset_name!r}"
                r.update(width=p["width"], height=p["height"], depth=p["depth"], preset=p["name"])
                return f"rack preset {p['name']}"
            for k, v in (("width", width), ("height", height), ("depth", depth)):
                if v is not None and v != r.get(k):
                    if not (np.isfinite(v) and 0 < v <= 100):
                        return f"⚠ rack {k} must be between 0 and 100 m"
                    r[k] = float(v)
                    r["preset"] = None
            return "rack size changed" if r != before_rack else ""
        return self.act(st, upd)

    def set_status(self, st: dict, status: str) -> dict:
        if status not in S.STATUSES:
            st["msg"] = f"unknown status {status!r}"
            return st

        def upd(a):
            a["status"] = status
            return f"status: {status}"
        return self.act(st, upd)

    # --- proposals ---------------------------------------------------------------------------
    def prediction(self, name: str) -> dict:
        with self._lock:
            if name not in self._preds:
                self._preds[name] = self.predictor.predict(self.image(name))
                while len(self._preds) > 8:
                    self._preds.popitem(last=False)
            return self._preds[name]

    def refresh_proposals(self, ann: dict) -> str:
        """Recompute the model's box proposals for the current corners and shelves (skipping
        those that overlap a box already there or one the labeller rejected)."""
        scene = self._scene(ann)
        if scene is None:
            ann["proposals"] = []
            return ""
        pred = self.prediction(ann["image"])
        if "front" not in pred:
            return "model has no front view: no proposals"
        if not scene.shelf_v:
            n = int(sum((pred["front"][i] == L.BOX).any() for i in range(pred["front"].shape[0])))
            ann["proposals"] = []
            return f"model ready ({n} shelf channel(s) with boxes): mark the shelves to see its box proposals"
        probs = pred.get("probs", {}).get("front")
        props = G.front_box_rects(pred["front"], pred.get("top"), pred["grid"], scene.shelf_v, scene.width,
                                  scene.depth, probs_box=None if probs is None else probs[:, L.BOX],
                                  tops=[v + c for v, c in zip(scene.shelf_v, scene.clear)])
        have = [(b.shelf, (b.u0, b.u1, b.v0, b.v1)) for b in scene.boxes]
        rejected = [(int(r[0]), tuple(r[1:])) for r in ann.get("rejected", [])]
        out = []
        nid = max([b["id"] for b in ann["boxes"]] + [999], default=999) + 1
        for p in props:
            rect = (p.u0, p.u1, p.v0, p.v1)
            if any(s == p.shelf and G.rect_iou(rect, r) > 0.3 for s, r in have + rejected):
                continue
            out.append(G.proposal_to_box(scene.plane, p, nid))
            nid += 1
        ann["proposals"] = out
        return f"model proposes {len(out)} box(es): select to accept (a) or reject (r)"

    def accept(self, st: dict, all_: bool = False) -> dict:
        sel = st.get("sel")
        if not all_ and (not sel or sel[0] != "proposal"):
            st["msg"] = "select a proposal first (mode 4)"
            return st

        def upd(a):
            take = [p for p in a.get("proposals", []) if all_ or p["id"] == sel[1]]
            for p in take:
                b = dict(p, id=_next_id(a["boxes"]), source="model")
                a["boxes"].append(b)
            a["proposals"] = [p for p in a.get("proposals", []) if p not in take]
            return f"accepted {len(take)} proposal(s)"
        st["sel"] = None
        return self.act(st, upd)

    def reject(self, st: dict) -> dict:
        sel = st.get("sel")
        if not sel or sel[0] != "proposal":
            st["msg"] = "select a proposal first (mode 4)"
            return st

        def upd(a):
            scene = self._scene(a)
            for p in a.get("proposals", []):
                if p["id"] == sel[1]:
                    if scene is not None:
                        mb = G.metric_box(scene.plane, p, scene.shelf_v, scene.depth, scene.depth)
                        if mb.shelf is not None:
                            a.setdefault("rejected", []).append(
                                [mb.shelf, round(mb.u0, 4), round(mb.u1, 4), round(mb.v0, 4), round(mb.v1, 4)])
                    a["proposals"] = [q for q in a["proposals"] if q["id"] != sel[1]]
                    return f"proposal rejected"
        st["sel"] = None
        return self.act(st, upd)

    # --- geometry and drawing --------------------------------------------------------------
    def _scene(self, ann: dict) -> G.Scene | None:
        try:
            return G.build_scene(ann, self.project.settings)
        except (G.GeometryError, ValueError):
            return None

    def _box_poly(self, scene, b) -> np.ndarray:
        if scene is not None:
            return G.box_outline(scene.plane, G.metric_box(scene.plane, b, scene.shelf_v or [-1e9], scene.depth, scene.depth))
        (x0, y0), (x1, y1) = b["p0"], b["p1"]
        return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)

    def layouts(self, ann: dict):
        scene = self._scene(ann)
        if scene is None or not scene.shelf_v:
            return scene, None, None
        st = self.project.settings
        try:
            top, front = scene.layouts(st["R"], L.Grid(st["D"], st["extent"]))
        except G.GeometryError:
            return scene, None, None
        return scene, top, front

    def render_photo(self, st: dict) -> np.ndarray | None:
        import cv2

        if st.get("name") is None:
            return None
        img = self.image(st["name"])
        a = st.get("ann")
        if a is None:
            return img
        x0, y0, z = self.view(st)
        H, W = img.shape[:2]
        if z != 1:
            zoom = max(1.0, float(st.get("zoom") or 1.0))
            crop = img[int(y0):int(np.ceil(y0 + H / zoom)), int(x0):int(np.ceil(x0 + W / zoom))]
            canvas = cv2.resize(crop, (int(round(crop.shape[1] * z)), int(round(crop.shape[0] * z))),
                                interpolation=cv2.INTER_LINEAR)
        else:
            canvas = img.copy()
        t = max(1, int(round(max(canvas.shape[:2]) / 450)))

        def P(pts):
            p = (np.asarray(pts, float).reshape(-1, 2) - [x0, y0] + 0.5) * z - 0.5
            return np.round(p).astype(np.int32)

        sel = st.get("sel") or [None, None]
        corners = a["rack"]["corners"]
        scene, top, front = self.layouts(a)
        scene = scene or self._scene(a)
        if len(corners) == 4:
            cv2.polylines(canvas, [P(G.order_corners(corners))], True, C_RACK, t, cv2.LINE_AA)
        for k, q in enumerate(corners):
            c = tuple(int(v) for v in P(q)[0])
            cv2.circle(canvas, c, 3 * t + (2 * t if sel == ["corner", k] else 0),
                       C_SEL if sel == ["corner", k] else C_RACK, -1, cv2.LINE_AA)
        if scene is not None:
            for k, (sid, v) in enumerate(zip(scene.shelf_ids, scene.shelf_v)):
                seg = P(G.shelf_line(scene.plane, v))
                cv2.line(canvas, tuple(seg[0]), tuple(seg[1]), C_SEL if sel == ["shelf", sid] else C_SHELF,
                         2 * t if sel == ["shelf", sid] else t, cv2.LINE_AA)
                cv2.putText(canvas, f"S{k + 1}", (int(seg[0][0]) + 3 * t, int(seg[0][1]) - 3 * t),
                            cv2.FONT_HERSHEY_SIMPLEX, 0.4 * t, C_SHELF, max(1, t // 2), cv2.LINE_AA)
            imp = read_imported(self.project, a) if a.get("imported") else {}
            if "front" in imp and scene.shelf_v:
                grid = L.Grid(imp["front"].shape[-1], self.project.settings["extent"])
                for p in G.front_box_rects(imp["front"], imp.get("top"), grid, scene.shelf_v, scene.width, scene.depth):
                    cv2.polylines(canvas, [P(G.rect_outline(scene.plane, p.u0, p.u1, p.v0, p.v1))], True, C_IMPORT, t, cv2.LINE_4)
        else:
            for s in a["shelves"]:
                cv2.drawMarker(canvas, tuple(int(v) for v in P(s["point"])[0]), C_SHELF, cv2.MARKER_CROSS, 8 * t, t)
        for kind, items, col in (("proposal", a.get("proposals", []), C_PROP), ("box", a["boxes"], C_BOX)):
            for b in items:
                poly = self._box_poly(scene, b)
                colour = col
                if kind == "box" and scene is not None and scene.shelf_v:
                    mb = G.metric_box(scene.plane, b, scene.shelf_v, scene.depth, scene.depth)
                    colour = C_FLOAT if mb.shelf is None else col
                chosen = sel == [kind, b["id"]]
                cv2.polylines(canvas, [P(poly)], True, C_SEL if chosen else colour, (2 * t if chosen else t), cv2.LINE_AA)
                if kind == "proposal":
                    cv2.putText(canvas, "?", tuple(int(v) for v in P(poly[3])[0]), cv2.FONT_HERSHEY_SIMPLEX,
                                0.5 * t, C_PROP, max(1, t // 2), cv2.LINE_AA)
        if st.get("pending"):
            cv2.drawMarker(canvas, tuple(int(v) for v in P(st["pending"])[0]), C_PEND, cv2.MARKER_TILTED_CROSS, 10 * t, t)
        return canvas

    def render_preview(self, st: dict, tile: int = 150) -> np.ndarray | None:
        """Every shelf's top (upper row) and front (lower row) layout, colourised, lowest shelf
        on the left; imported layouts (read-only) in two more rows when the image has them."""
        import cv2

        a = st.get("ann")
        if a is None:
            return None
        _, top, front = self.layouts(a)
        rows = []
        if top is not None:
            rows += [("top", top), ("front", front)]
        imp = read_imported(self.project, a) if a.get("imported") else {}
        rows += [(f"imported {v} (read-only)", imp[v]) for v in L.VIEWS if v in imp]
        if not rows:
            return None
        R = max(s.shape[0] for _, s in rows)
        lo, hi = content_window([s for _, s in rows])
        pad, head = 4, 16
        out = np.full((len(rows) * (tile + head + pad) + pad, R * (tile + pad) + pad, 3), 245, np.uint8)
        for r, (label, stack) in enumerate(rows):
            yb = pad + r * (tile + head + pad)
            for i in range(stack.shape[0]):
                xb = pad + i * (tile + pad)
                img = cv2.resize(colorize(stack[i, lo:hi, lo:hi]), (tile, tile), interpolation=cv2.INTER_NEAREST)
                out[yb + head:yb + head + tile, xb:xb + tile] = img
                cv2.putText(out, f"S{i + 1} {label}", (xb, yb + head - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.38,
                            (30, 30, 30), 1, cv2.LINE_AA)
        return out

    def summary(self, st: dict) -> str:
        a = st.get("ann")
        if a is None:
            return ""
        scene, top, front = self.layouts(a)
        n_c = len(a["rack"]["corners"])
        r = a["rack"]
        lines = [f"**Rack** {n_c}/4 corners · {r['width']} × {r['height']} × {r['depth']} m"
                 + (f" ({r['preset']})" if r.get("preset") else "")]
        if scene is not None:
            for i, (v, c) in enumerate(zip(scene.shelf_v, scene.clear)):
                nb = sum(b.shelf == i for b in scene.boxes)
                px = ""
                if top is not None and i < top.shape[0]:
                    px = (f" · box px top {int((top[i] == L.BOX).sum())}, front {int((front[i] == L.BOX).sum())}")
                lines.append(f"- **S{i + 1}** board {v:.2f} m, clear {c:.2f} m, {nb} box(es){px}")
            lines += [f"- ⚠ {w}" for w in scene.warnings]
        else:
            lines.append(f"- {len(a['shelves'])} shelf click(s), {len(a['boxes'])} box(es)")
        R = self.project.settings["R"]
        if len(a["shelves"]) > R:
            lines.append(f"- ⚠ {len(a['shelves'])} shelves marked but the project has R={R} channels: "
                         f"delete {len(a['shelves']) - R} (the export refuses this image)")
        if a.get("proposals"):
            lines.append(f"- {len(a['proposals'])} model proposal(s) waiting (green)")
        return "\n".join(lines)

    def header(self, st: dict) -> str:
        done, n = self.project.progress()
        names = self.project.images()
        name = st.get("name")
        k = names.index(name) + 1 if name in names else 0
        status = st["ann"]["status"] if st.get("ann") else "—"
        return f"**{done} of {n} done** · image {k}/{n}: `{name}` · status **{status}** · mode **{st.get('mode')}**"

    def selection(self, st: dict) -> tuple[str, float | None, float | None]:
        sel = st.get("sel")
        a = st.get("ann")
        if not sel or a is None:
            return "nothing selected", None, None
        kind, key = sel
        if kind in ("box", "proposal"):
            for b in a["boxes"] if kind == "box" else a.get("proposals", []):
                if b["id"] == key:
                    scene = self._scene(a)
                    txt = f"{kind} {key} ({b.get('source', 'manual')})"
                    if scene is not None:
                        mb = G.metric_box(scene.plane, b, scene.shelf_v, scene.depth, scene.depth)
                        where = f"shelf S{mb.shelf + 1}" if mb.shelf is not None else "no shelf"
                        txt += f": x {mb.u0 - scene.width / 2:+.2f}…{mb.u1 - scene.width / 2:+.2f} m, height {mb.v1 - mb.v0:.2f} m, on {where}"
                    return txt, b.get("depth"), b.get("front_offset", 0.0)
        return f"{kind} {key + 1 if kind == 'corner' else key}", None, None


def _content(a: dict) -> dict:
    return {k: v for k, v in a.items() if k not in ("version", "updated_at", "updated_by")}


def _next_id(items) -> int:
    return max((int(i["id"]) for i in items), default=-1) + 1


def _inside(poly, pt) -> bool:
    import cv2

    return cv2.pointPolygonTest(np.asarray(poly, np.float32), (float(pt[0]), float(pt[1])), False) >= 0


def _poly_area(poly) -> float:
    x, y = np.asarray(poly)[:, 0], np.asarray(poly)[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _seg_dist(seg, pt) -> float:
    a, b, p = np.asarray(seg[0], float), np.asarray(seg[1], float), np.asarray(pt, float)
    d = b - a
    t = np.clip(np.dot(p - a, d) / max(np.dot(d, d), 1e-12), 0, 1)
    return float(np.linalg.norm(a + t * d - p))


# --- the gradio UI ------------------------------------------------------------------------------
#: gradio's delete_cache: every minute, remove the files this app put in gradio's cache (rendered
#: photos, uploads, accepted or refused) once they are 5 minutes old
DELETE_CACHE = (60, 300)


def build_app(project: Project, predictor=None, user: str | None = None, tmp_dir: str | None = None):
    import gradio as gr

    tool = Tool(project, predictor, user, tmp_dir=tmp_dir)
    presets = [p["name"] for p in project.settings["presets"]]

    with gr.Blocks(title="RackLay annotate", delete_cache=DELETE_CACHE) as demo:
        state = gr.State(None)
        header = gr.Markdown(elem_id="header")
        with gr.Row():
            btn_prev = gr.Button("◀ prev", elem_id="btn-prev", size="sm", scale=0)
            image_dd = gr.Dropdown(choices=project.images(), label="photo file", elem_id="image-select", scale=3)
            btn_next = gr.Button("next ▶", elem_id="btn-next", size="sm", scale=0)
            status_dd = gr.Dropdown(choices=list(S.STATUSES), label="annotation status", elem_id="status", scale=2)
            btn_done = gr.Button("mark done (d)", elem_id="btn-done", size="sm", scale=0)
        with gr.Row(elem_classes="mode-row"):
            mode_btns = {m: gr.Button(f"{i + 1} {m}", elem_id=f"mode-{m}", size="sm") for i, m in enumerate(MODES)}
        mode_help = gr.Markdown(elem_id="mode-help")
        with gr.Row():
            with gr.Column(scale=3):
                photo = gr.Image(type="filepath", interactive=False, buttons=[], show_label=False,
                                 elem_id="photo", height=DISPLAY_H)
                message = gr.Markdown(elem_id="message")
            with gr.Column(scale=2):
                gr.Markdown("**Live layouts** — per shelf (S1 = lowest): top view above, front view below; "
                            "orange = box, blue = free shelf space")
                preview = gr.Image(type="numpy", format="png", interactive=False, buttons=[], show_label=False,
                                   elem_id="preview")
                summary = gr.Markdown(elem_id="summary")
        with gr.Row():
            with gr.Column():
                gr.Markdown("**Rack**")
                preset_dd = gr.Dropdown(choices=presets, label="preset", elem_id="preset")
                with gr.Row():
                    width_n = gr.Number(label="width m", elem_id="rack-width", minimum=0)
                    height_n = gr.Number(label="height m", elem_id="rack-height", minimum=0)
                    depth_n = gr.Number(label="depth m", elem_id="rack-depth", minimum=0)
            with gr.Column():
                gr.Markdown("**Selection**")
                sel_md = gr.Markdown(elem_id="selection")
                with gr.Row():
                    box_depth = gr.Number(label="box depth m (empty: shelf depth)", elem_id="box-depth", minimum=0)
                    box_off = gr.Number(label="front offset m", elem_id="box-offset", minimum=0)
                with gr.Row():
                    btn_delete = gr.Button("delete (Del)", elem_id="btn-delete", size="sm")
                    btn_accept = gr.Button("accept (a)", elem_id="btn-accept", size="sm")
                    btn_reject = gr.Button("reject (r)", elem_id="btn-reject", size="sm")
                    btn_accept_all = gr.Button("accept all (A)", elem_id="btn-accept-all", size="sm")
            with gr.Column():
                gr.Markdown("**Edit & view**")
                with gr.Row():
                    btn_undo = gr.Button("undo (z)", elem_id="btn-undo", size="sm")
                    btn_redo = gr.Button("redo (y)", elem_id="btn-redo", size="sm")
                    btn_save = gr.Button("save (s)", elem_id="btn-save", size="sm")
                    btn_cancel = gr.Button("cancel box (Esc)", elem_id="btn-cancel", size="sm")
                with gr.Row():
                    btn_zin = gr.Button("zoom + ", elem_id="btn-zoom-in", size="sm")
                    btn_zout = gr.Button("zoom −", elem_id="btn-zoom-out", size="sm")
                    btn_zreset = gr.Button("zoom 1:1", elem_id="btn-zoom-reset", size="sm")
                upload = gr.File(label="add photos (PNG/JPEG)", file_count="multiple", file_types=[".png", ".jpg", ".jpeg"],
                                 elem_id="upload")
        with gr.Accordion("Keyboard shortcuts", open=True):
            gr.Markdown("\n".join(["| key | action |", "|---|---|"] + [f"| {k} | {v} |" for k, v, _ in SHORTCUTS]),
                        elem_id="shortcuts")

        outputs = [state, header, image_dd, status_dd, preset_dd, width_n, height_n, depth_n, photo, preview,
                   summary, message, mode_help, sel_md, box_depth, box_off] + list(mode_btns.values())

        def render(st):
            sel_txt, bd, bo = tool.selection(st)
            a = st.get("ann") or {}
            rack = a.get("rack") or {}
            names = project.images()
            return [st, tool.header(st), gr.update(choices=names, value=st.get("name")),
                    a.get("status"), rack.get("preset"), rack.get("width"), rack.get("height"), rack.get("depth"),
                    tool.photo_file(st), tool.render_preview(st), tool.summary(st), st.get("msg", ""),
                    f"**{st.get('mode')}**: {MODE_HELP.get(st.get('mode'), '')}", sel_txt, bd, bo] + [
                gr.update(variant="primary" if m == st.get("mode") else "secondary") for m in MODES]

        def ensure(st):
            return st if st is not None else tool.open(project.resume_image())

        def on_load(request: gr.Request):
            # the logged-in user (--auth-file) is kept in the session state and recorded on saves
            return render(tool.open(project.resume_image(), getattr(request, "username", None)))

        def on_select(st, evt: gr.SelectData):
            st = ensure(st)
            x, y = evt.index
            return render(tool.click(st, float(x), float(y)))

        def wrap(fn):
            def h(st, *args):
                return render(fn(ensure(st), *args))
            return h

        def set_mode(m):
            def h(st):
                st = ensure(st)
                st["mode"], st["pending"] = m, None
                st["msg"] = ""
                return render(st)
            return h

        def zoom(f):
            def h(st):
                st = ensure(st)
                st["zoom"] = 1.0 if f == 0 else float(np.clip(st.get("zoom", 1.0) * f, 1.0, 8.0))
                st["msg"] = f"zoom {st['zoom']:g}×"
                return render(st)
            return h

        def cancel(st):
            st["pending"] = None
            st["msg"] = "box cancelled"
            return st

        def on_upload(st, files):
            st = ensure(st)
            added, errs = [], []
            for f in files or []:
                path = f if isinstance(f, str) else getattr(f, "name", str(f))
                try:
                    with open(path, "rb") as fh:
                        data = fh.read()
                    added.append(project.add_image(os.path.basename(path), data))
                except (StoreError, OSError) as e:
                    errs.append(str(e))
                finally:
                    with contextlib.suppress(OSError):   # gradio's copy of the upload: done with it
                        os.unlink(path)
            if added and st.get("name") is None:
                st = tool.open(added[0], st.get("user"))
            st["msg"] = (f"added {', '.join(added)}" if added else "") + (("; ⚠ " + "; ⚠ ".join(errs)) if errs else "")
            return render(st)

        demo.load(on_load, None, outputs)
        photo.select(on_select, [state], outputs)
        image_dd.input(wrap(lambda st, name: tool.open(name, st.get("user"))), [state, image_dd], outputs)
        btn_prev.click(wrap(lambda st: tool.step(st, -1)), [state], outputs)
        btn_next.click(wrap(lambda st: tool.step(st, +1)), [state], outputs)
        status_dd.input(wrap(lambda st, s: tool.set_status(st, s)), [state, status_dd], outputs)
        btn_done.click(wrap(lambda st: tool.set_status(st, "done")), [state], outputs)
        for m, b in mode_btns.items():
            b.click(set_mode(m), [state], outputs)
        preset_dd.input(wrap(lambda st, p: tool.set_rack(st, preset_name=p)), [state, preset_dd], outputs)
        # numbers are applied on Enter or when the field loses focus (not on every keystroke)
        for comp, fn in ((width_n, lambda st, v: tool.set_rack(st, width=v)),
                         (height_n, lambda st, v: tool.set_rack(st, height=v)),
                         (depth_n, lambda st, v: tool.set_rack(st, depth=v)),
                         (box_depth, lambda st, v: tool.set_box_field(st, "depth", v)),
                         (box_off, lambda st, v: tool.set_box_field(st, "front_offset", v))):
            comp.submit(wrap(fn), [state, comp], outputs)
            comp.blur(wrap(fn), [state, comp], outputs)
        btn_delete.click(wrap(tool.delete), [state], outputs)
        btn_accept.click(wrap(tool.accept), [state], outputs)
        btn_reject.click(wrap(tool.reject), [state], outputs)
        btn_accept_all.click(wrap(lambda st: tool.accept(st, all_=True)), [state], outputs)
        btn_undo.click(wrap(tool.undo), [state], outputs)
        btn_redo.click(wrap(lambda st: tool.undo(st, redo=True)), [state], outputs)
        btn_save.click(wrap(tool.save_now), [state], outputs)
        btn_cancel.click(wrap(cancel), [state], outputs)
        btn_zin.click(zoom(2.0), [state], outputs)
        btn_zout.click(zoom(0.5), [state], outputs)
        btn_zreset.click(zoom(0), [state], outputs)
        upload.upload(on_upload, [state, upload], outputs)
    demo.tool = tool
    return demo


def launch_kwargs(host: str = "127.0.0.1", port: int = 7860, auth=None) -> dict:
    """Everything launch() needs to run offline: built-in theme with system fonts, our css and
    keyboard script, no SSR node server, upload size limit."""
    import gradio as gr

    from .store import MAX_UPLOAD_BYTES

    theme = gr.themes.Soft(font=["ui-sans-serif", "system-ui", "sans-serif"],
                           font_mono=["ui-monospace", "monospace"])
    return dict(server_name=host, server_port=port, auth=auth, theme=theme, css=CSS, head=_head(),
                ssr_mode=False, max_file_size=MAX_UPLOAD_BYTES, show_error=True, quiet=True, footer_links=[])


def load_predictor(model: str | None, backend: str = "torch"):
    if not model:
        return None
    from racklay.predict import Predictor

    return Predictor(model, backend=backend)


class PortError(ValueError):
    """The server cannot listen on the requested address and port."""


def _port_message(host: str, port: int, reason: str, hint: str = "choose another --port") -> str:
    return f"cannot serve on {host}:{port} ({reason}); {hint}"


def check_port(host: str, port: int) -> None:
    """Refuse a port that cannot be bound before the app (and a model) is loaded. Binds the way
    gradio does (SO_REUSEADDR), then lets go at once."""
    import socket

    if not 1 <= port <= 65535:
        raise PortError(f"--port: {port} is not a port number (1-65535)")
    bind_host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    try:
        infos = socket.getaddrinfo(bind_host, port, type=socket.SOCK_STREAM)
    except OSError as e:
        raise PortError(_port_message(host, port, f"unknown address: {e.strerror or type(e).__name__}",
                                      "check --host")) from None
    family, _, _, _, addr = infos[0]
    try:
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(addr)
    except OSError as e:
        import errno

        reason = (e.strerror or type(e).__name__).lower()
        if e.errno == errno.EADDRNOTAVAIL:
            raise PortError(_port_message(host, port, f"{reason}: not an address of this machine",
                                          "check --host")) from None
        raise PortError(_port_message(host, port, reason)) from None


def run_temp_dir() -> str:
    """A temp folder for this server run, holding gradio's cache (rendered photos, uploads) and the
    viewer's images; removed when the process exits (serve() makes SIGTERM a normal exit)."""
    import atexit
    import shutil
    import tempfile

    path = tempfile.mkdtemp(prefix="annotate-run-")
    os.environ["GRADIO_TEMP_DIR"] = os.path.join(path, "gradio")   # read by gradio's blocks and routes
    atexit.register(shutil.rmtree, path, True)
    return path


def exit_on_sigterm() -> None:
    """SIGTERM (`kill`, systemd, docker stop) becomes a normal exit, so atexit clean-up runs."""
    import signal
    import sys

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))


def _drop_temp_dir(path: str, env_before: str | None) -> None:
    """Undo run_temp_dir() when serve() fails to start."""
    import shutil

    shutil.rmtree(path, ignore_errors=True)
    if env_before is None:
        os.environ.pop("GRADIO_TEMP_DIR", None)
    else:
        os.environ["GRADIO_TEMP_DIR"] = env_before


def serve(project_dir, host: str = "127.0.0.1", port: int = 7860, model: str | None = None,
          backend: str = "torch", auth=None, block: bool = True):
    """Serve the tool. `auth`: None (no login) or an annotate.auth.Authenticator (several users,
    throttled failed logins; each save records the logged-in user)."""
    check_port(host, port)
    project = Project(project_dir)
    env_before = os.environ.get("GRADIO_TEMP_DIR")
    tmp = run_temp_dir()
    try:
        demo = build_app(project, load_predictor(model, backend), tmp_dir=tmp)
        kw = launch_kwargs(host, port, auth.check if auth is not None else None)
        try:
            demo.launch(prevent_thread_lock=True, **kw)
        except OSError as e:
            if "Cannot find empty port" not in str(e):
                raise
            raise PortError(_port_message(host, port, "the port is in use")) from None
    except BaseException:
        _drop_temp_dir(tmp, env_before)
        raise
    if block:
        exit_on_sigterm()
    print(f"annotate: serving {project.root} ({len(project.images())} images) at http://{host}:{port}"
          + (f", pre-labels from {os.path.basename(str(model))}" if model else ""))
    if block:
        demo.block_thread()
    return demo
