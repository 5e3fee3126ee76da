"""The annotation tool's logic, with no UI: `Tool` applies every action of the page (a click, a
key, a typed number) to a typed annotate.session.Session and the labeller's annotation, saves it at
once through annotate.store (atomic, version-checked; this module never touches the files) and
says what the page must show (annotate.draw builds it). The labeller clicks the rack's four
corners, one point on each shelf board's front edge and two opposite corners of each box's front
face; annotate.geometry turns the clicks into metric shelves and boxes, and racklay.layout draws
every shelf's top and front layout.

The gradio app around it is annotate.app; the server (ports, temporary files, serve) is
annotate.server; the page itself (viewer, keys, how a click travels) is annotate.page.
"""
import contextlib
import copy
import json
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, replace

import numpy as np

from racklay import layout as L
from racklay.data import luminance
from racklay.reasoning import ReasoningConfig

from . import draw as D
from . import geometry as G
from . import schema as S
from .session import FILTERS, MODES, Session
from .store import DONE_STATUSES, ConflictError, Project, StoreError


@dataclass
class _Derived:
    """What the geometry makes of one annotation's rack, shelves and boxes: its scene (or why
    there is none) and, computed when first asked for, its layouts."""

    scene: G.Scene | None
    error: str | None = None
    layouts: tuple | None = None


class Tool:
    """Server-side logic, independent of gradio: each method takes and returns the session (an
    annotate.session.Session), so it can be tested without a browser. Clicks are in photo
    pixels. What the page shows is drawn by annotate.draw from frame(); the annotation's scene is
    built once for each new rack, shelves and boxes and shared by the edit, the outlines, the
    texts and the preview."""

    def __init__(self, project: Project, predictor=None, user: str | None = None):
        self.project = project
        self.predictor = predictor
        self.user = user
        #: how the model's layouts are read into box proposals (racklay.reasoning's knobs); no cut
        #: where a box region's top steps: the photo's gaps cut better (docs/annotate.md, measured)
        self.reasoning = replace(ReasoningConfig(), split_step_m=0.0)
        #: how a proposal is cut where the photo shows a gap along it (depth 0: never)
        self.gap_split = G.GapSplit()
        #: the model reads the photo cropped to the rack the labeller outlined (False: the whole photo)
        self.read_rack_crop = True
        self._images: OrderedDict[str, np.ndarray] = OrderedDict()
        self._photo_b64: OrderedDict[str, str] = OrderedDict()
        self._preds: OrderedDict[tuple, dict] = OrderedDict()   # (photo, rack corners or None)
        self._luma: OrderedDict[str, np.ndarray] = OrderedDict()
        self._derived: OrderedDict[str, _Derived] = OrderedDict()
        self._lock = threading.RLock()
        self._history: dict[str, tuple] = {}     # undo history waiting to be written, per photo
        self._history_cv = threading.Condition()
        self._history_busy = False
        threading.Thread(target=self._history_writer, daemon=True, name="annotate-history").start()

    def photo_b64(self, name: str) -> str:
        """The photo as the browser shows it (annotate.draw.photo_jpeg_b64), encoded once per photo."""
        with self._lock:
            if name not in self._photo_b64:
                self._photo_b64[name] = D.photo_jpeg_b64(self.image(name))
                while len(self._photo_b64) > 4:
                    self._photo_b64.popitem(last=False)
            self._photo_b64.move_to_end(name)
            return self._photo_b64[name]

    # --- state ---------------------------------------------------------------------------
    def open(self, name: str | None, user: str | None = None, keep: Session | None = None) -> Session:
        """A session for image `name`; `user` is the logged-in user (saves record it).
        `keep`: the previous session, whose list filter and action counter carry over."""
        st = Session(name=name, user=user)
        if keep is not None:
            st.filter, st.ack = keep.filter, keep.ack
        if name is None:
            st.msg = "no images in the project yet: upload some"
            return st
        try:
            why = self.project.photo_problem(name)
            if why:
                raise StoreError(why)
            ann = self.project.load(name)
        except (S.SchemaError, StoreError) as e:
            st.error = str(e)
            st.msg = f"⚠ {e} — this file is not overwritten; fix or delete it by hand"
            return st
        try:
            self.image(name)
        except (StoreError, ValueError) as e:   # a header that looked fine, pixels that do not decode
            self.project.mark_unreadable(name, str(e))
            st.error = str(e)
            st.msg = f"⚠ {e} — listed as unreadable; the rest of the project works"
            return st
        st.ann = ann
        self.flush_history()
        st.undo, st.redo = self.project.load_history(name, ann["version"])
        with contextlib.suppress(OSError, StoreError):
            self.project.set_last_opened(name, user)
        rack = ann["rack"]
        st.mode = "corners" if len(rack["corners"]) < 4 else ("shelves" if not ann["shelves"] else "boxes")
        hist = f", {len(st.undo)} undo step(s)" if st.undo else ""
        st.msg = f"opened {name} (version {ann['version']}, {ann['status']}{hist})"
        return st

    def image(self, name: str) -> np.ndarray:
        with self._lock:
            if name not in self._images:
                self._images[name] = self.project.read_image(name)
                while len(self._images) > 8:
                    self._images.popitem(last=False)
            self._images.move_to_end(name)
            return self._images[name]

    def listed(self, st: Session, stats: dict[str, str] | None = None) -> list[str]:
        """The photos the list shows under the session's filter (the open one always).
        `stats`: the project's statuses, when the caller has them."""
        f = st.filter
        stats = self.project.statuses() if stats is None else stats
        keep = {"all": lambda s: True, "unfinished": lambda s: s not in DONE_STATUSES + ("unreadable",)}.get(
            f, lambda s: s == f)
        return [n for n, s in stats.items() if keep(s) or n == st.name]

    def step(self, st: Session, delta: int, unfinished: bool = False) -> Session:
        """The next (previous) photo in the list's filter, or the next unfinished one; unreadable
        photos are skipped."""
        stats = self.project.statuses()
        names = list(stats)
        if not names:
            return self.open(None, st.user, st)
        if unfinished:
            ok = [n for n in names if stats[n] not in DONE_STATUSES + ("unreadable", "invalid")]
        else:
            ok = [n for n in self.listed(st, stats) if stats[n] != "unreadable" or n == st.name]
        cur = st.name
        i = names.index(cur) if cur in names else -1
        for k in range(1, len(names) + 1):
            n = names[(i + delta * k) % len(names)]
            if n in ok and n != cur:
                return self.open(n, st.user, st)
        st.msg = "no unfinished photo left: all done" if unfinished else "no other photo in this list"
        return st

    # --- applying an edit: save at once, with undo ----------------------------------------
    def act(self, st: Session, fn) -> Session:
        if st.ann is None:
            st.msg = st.msg or "nothing to edit"
            return st
        before = st.ann
        ann = copy.deepcopy(before)
        msg = fn(ann)
        if _content(ann) == _content(before):
            st.msg = msg or st.msg
            return st
        if ann["status"] == before["status"] == "todo":
            ann["status"] = "in progress"
        if self.predictor is not None and (ann["rack"] != before["rack"] or ann["shelves"] != before["shelves"]):
            pm = self.refresh_proposals(ann)
            msg = f"{msg}; {pm}" if msg and pm else (msg or pm)
        if self._save(st, ann):
            st.undo.append(before)
            st.undo = st.undo[-200:]
            st.redo = []
            self._keep_history(st)
            st.msg = msg or f"saved (version {st.ann['version']})"
        return st

    def _keep_history(self, st: Session) -> None:
        """Hand the undo history to the writer thread (off the click's path; the newest wins)."""
        with self._history_cv:
            self._history[st.name] = (st.ann["version"], list(st.undo), list(st.redo))
            self._history_cv.notify()

    def _history_writer(self) -> None:
        while True:
            with self._history_cv:
                while not self._history:
                    self._history_cv.wait()
                name, (version, undo, redo) = self._history.popitem()
                self._history_busy = True
            try:
                with contextlib.suppress(OSError, StoreError):
                    self.project.save_history(name, version, undo, redo)
            finally:
                with self._history_cv:
                    self._history_busy = False
                    self._history_cv.notify_all()

    def flush_history(self, timeout: float = 10.0) -> None:
        """Until every waiting undo history is written (tests; a new page load reads it)."""
        with self._history_cv:
            self._history_cv.wait_for(lambda: not self._history and not self._history_busy, timeout)

    def _save(self, st: Session, ann: S.Annotation) -> bool:
        try:
            st.ann = self.project.save(ann, user=st.user or self.user)
            return True
        except ConflictError as e:
            st.msg = f"⚠ {e}"
        except (S.SchemaError, StoreError) as e:
            st.msg = f"⚠ not saved: {e}"
        return False

    def undo(self, st: Session, redo: bool = False) -> Session:
        src, dst = (st.redo, st.undo) if redo else (st.undo, st.redo)
        if st.ann is None or not src:
            st.msg = f"nothing to {'redo' if redo else 'undo'}"
            return st
        target = copy.deepcopy(src[-1])
        current = st.ann
        target["version"] = current["version"]
        if self._save(st, target):
            src.pop()
            dst.append(current)
            st.sel, st.pending = None, None
            self._keep_history(st)
            st.msg = f"{'redone' if redo else 'undone'} (version {st.ann['version']})"
        return st

    def save_now(self, st: Session) -> Session:
        if st.ann is None:
            return st
        if self._save(st, copy.deepcopy(st.ann)):
            self._keep_history(st)
            st.msg = f"saved (version {st.ann['version']})"
        return st

    # --- the page's actions, in order ------------------------------------------------------
    def apply(self, st: Session, actions) -> Session:
        """Apply a batch of the page's actions in order. Each has a sequence number `seq`; one
        already applied is skipped (a batch sent again after a lost answer). A malformed action
        is reported in the message and skipped."""
        for a in actions if isinstance(actions, list) else []:
            seq = a.get("seq") if isinstance(a, dict) else None
            if isinstance(seq, int) and seq <= st.ack:
                continue
            try:
                st = self.apply_one(st, a)
            except (ValueError, TypeError, KeyError, AttributeError) as e:
                st.msg = f"⚠ ignored a malformed request ({type(e).__name__}: {e})"
            if isinstance(seq, int):
                st.ack = seq
        return st

    def apply_one(self, st: Session, a: dict) -> Session:
        kind = a["kind"]
        img = a.get("image")
        # an action that asked for a second key press is armed for the very next action only
        armed, st.confirm = st.confirm, None
        if kind in ("click", "box", "drag", "field") and img is not None and img != st.name:
            st.msg = f"a {kind} made on {img} was not applied: {st.name} is open now"
            return st
        if kind == "click":
            return self.click(st, _finite(a["x"]), _finite(a["y"]), zoom=_finite(a.get("z", 1.0)))
        if kind in ("box", "drag"):
            p0 = [_finite(a["p0"][0]), _finite(a["p0"][1])]
            p1 = [_finite(a["p1"][0]), _finite(a["p1"][1])]
            if kind == "drag":
                return self.drag(st, p0, p1, zoom=_finite(a.get("z", 1.0)))
            st.pending = None
            return self.add_box(st, p0, p1)
        if kind == "mode":
            if a["mode"] not in MODES:
                raise ValueError(f"unknown mode {a['mode']!r}")
            if a["mode"] in ("depth", "offset") and st.mode not in ("depth", "offset"):
                st.mode_before = st.mode
            st.mode, st.pending, st.grab = a["mode"], None, None
            st.msg = ""
            return st
        if kind == "field":
            return self.set_field(st, a["field"], a.get("text"))
        if kind == "preset":
            return self.set_rack(st, preset_name=a["name"])
        if kind == "status":
            return self.set_status(st, a["value"])
        if kind == "open":
            name = a["name"]
            if name not in self.project.images():
                raise ValueError(f"no photo {name!r} in the project")
            return self.open(name, st.user, st)
        if kind == "filter":
            if a["value"] not in FILTERS:
                raise ValueError(f"unknown filter {a['value']!r}")
            st.filter = a["value"]
            n = len(self.listed(st))
            st.msg = f"list: {a['value']} ({n} photo(s))"
            return st
        if kind == "act":
            fn = {"undo": self.undo, "redo": lambda s: self.undo(s, redo=True), "delete": self.delete,
                  "save": self.save_now, "done": lambda s: self.mark_done(s, armed), "accept": self.accept,
                  "reject": self.reject, "accept_all": lambda s: self.accept(s, all_=True), "cancel": self.cancel,
                  "next": lambda s: self.step(s, +1), "prev": lambda s: self.step(s, -1),
                  "next_unfinished": lambda s: self.step(s, +1, unfinished=True),
                  "confirm_size": self.confirm_size, "toggle_on_board": self.toggle_on_board,
                  "size_from_box": self.size_from_box, "split_row": self.split_row,
                  "split_at_gaps": self.split_at_gaps}.get(a["name"])
            if fn is None:
                raise ValueError(f"unknown action {a['name']!r}")
            return fn(st)
        raise ValueError(f"unknown kind {kind!r}")

    def cancel(self, st: Session) -> Session:
        """Esc: drop a half-drawn box or a grabbed corner."""
        st.msg = "box cancelled" if st.pending is not None or st.grab is None else "corner let go"
        st.pending = st.grab = None
        return st

    # --- clicks (photo pixels: x right, y down, pixel centres at integers) -------------------
    def click(self, st: Session, x: float, y: float, zoom: float = 1.0) -> Session:
        """A click at photo pixel (x, y) in the current mode. `zoom`: how far the labeller had
        zoomed in (a closer look picks more precisely)."""
        if st.ann is None:
            return st
        pt = [round(float(x), 2), round(float(y), 2)]
        mode = st.mode
        if mode == "corners":
            return self.act(st, lambda a: self._corner(st, a, pt))
        if mode == "shelves":
            def add_shelf(a):
                a["shelves"].append({"id": _next_id(a["shelves"]), "point": pt})
                return f"shelf {len(a['shelves'])} marked"
            return self.act(st, add_shelf)
        if mode == "boxes":
            if st.pending is None:
                st.pending = pt
                st.msg = "now click the opposite corner of the box's front face"
                return st
            p0, st.pending = st.pending, None
            return self.add_box(st, p0, pt)
        if mode == "select":
            st.sel, st.grab = self.pick(st, pt, zoom), None
            st.msg = f"selected {st.sel[0]} {st.sel[1]}" if st.sel else "nothing here"
            return st
        if mode in ("move", "resize"):
            if not st.sel:
                st.msg = "select something first (mode 4)"
                return st
            if mode == "resize" and st.sel[0] in ("box", "proposal"):
                # two clicks: the first grabs the box corner nearest to it, the second puts it
                if st.grab is None:
                    st.grab = pt
                    st.msg = "corner grabbed: click where it should go (Esc: let go)"
                    return st
                grab, st.grab = st.grab, None
                return self.act(st, lambda a: self._resize(st.sel, a, grab, pt))
            return self.act(st, lambda a: self._move(st, a, pt))
        if mode in ("depth", "offset"):
            return self._depth_click(st, pt, mode)
        return st

    def add_box(self, st: Session, p0, p1) -> Session:
        def add(a):
            b = {"id": _next_id(a["boxes"]), "p0": list(p0), "p1": list(p1), "source": "manual"}
            a["boxes"].append(b)
            st.sel = ["box", b["id"]]
            return f"box {b['id']} added"
        return self.act(st, add)

    def _selected_box(self, st: Session) -> S.Box | None:
        if not st.sel or st.sel[0] != "box" or st.ann is None:
            return None
        return self._selected_item(st)

    @staticmethod
    def _selected_item(st: Session) -> S.Box | None:
        """The selected box or proposal (None if neither is selected or it is gone)."""
        if not st.sel or st.sel[0] not in ("box", "proposal") or st.ann is None:
            return None
        items = st.ann["boxes"] if st.sel[0] == "box" else st.ann.get("proposals", [])
        return next((b for b in items if b["id"] == st.sel[1]), None)

    def _depth_click(self, st: Session, pt, mode: str) -> Session:
        """A click on the selected box's top-back edge (depth) or on the board where its front
        stands (front offset), through the camera recovered from the rack plane."""
        b = self._selected_box(st)
        if b is None:
            st.msg = "select a box first (mode 4; a new box is selected)"
            return st
        scene = self.scene(st.ann)
        mb = next((m for m in scene.boxes if m.id == b["id"]), None) if scene is not None else None
        if mb is None or mb.shelf is None:
            st.msg = "mark the rack, its shelves and the box's shelf first"
            return st
        cam = G.camera_from_plane(scene.plane, st.ann["image_size"], S.pixel_aspect(self.project.settings))
        back, st.mode_before = st.mode_before or "boxes", None
        if mode == "depth":
            s = G.depth_from_click(cam, mb, pt, scene.depth)
            val = round(float(np.clip(s - mb.front_offset, 0.01, max(scene.depth - mb.front_offset, 0.01))), 3)
            field, what = "depth", "depth"
        else:
            o = G.offset_from_click(cam, scene.shelf_v[mb.shelf], pt)
            if o is None:
                st.msg = "⚠ that click is not on the top of the box's board: click where the box's front stands on it"
                return st
            val = round(float(np.clip(o, 0.0, max(scene.depth - 0.01, 0.0))), 3)
            field, what = "front_offset", "front offset"
        st.mode = back
        note = "" if cam.focal_from_photo else " (the view is nearly frontal: a typical phone lens is assumed; check it)"

        def upd(a):
            for x in a["boxes"]:
                if x["id"] == b["id"]:
                    x[field] = val
            return f"box {b['id']}: {what} {val:g} m from the click{note}"
        return self.act(st, upd)

    def _corner(self, st: Session, a, pt):
        c = a["rack"]["corners"]
        if a["rack"]["width"] is None:
            p = S.preset(self.project.settings, self.project.settings.get("default_preset"))
            if p:
                a["rack"].update(width=p["width"], height=p["height"], depth=p["depth"], preset=p["name"],
                                 size_confirmed=False)
        if len(c) < 4:
            c.append(pt)
            if len(c) == 4:
                st.mode = "shelves"
                return "4 corners set: now click each shelf board's front edge"
            return f"corner {len(c)} of 4"
        k = int(np.argmin([np.hypot(q[0] - pt[0], q[1] - pt[1]) for q in c]))
        c[k] = pt
        return f"corner {k + 1} moved"

    def drag(self, st: Session, p0, p1, zoom: float = 1.0) -> Session:
        """A drag on the photo from p0 to p1 (photo pixels). `boxes`: a new box with these
        opposite corners; `select`: takes the item under p0 along (a box grabbed near one of its
        corners is resized by that corner, otherwise moved by the drag); `move`: moves the
        selected item by the drag; `resize`: moves the selected box's corner nearest to p0 to
        p1. Other modes take it as a click at p0."""
        if st.ann is None:
            return st
        p0 = [round(float(p0[0]), 2), round(float(p0[1]), 2)]
        p1 = [round(float(p1[0]), 2), round(float(p1[1]), 2)]
        mode = st.mode
        if mode == "boxes":
            st.pending = None
            return self.add_box(st, p0, p1)
        if mode not in ("select", "move", "resize"):
            return self.click(st, p0[0], p0[1], zoom)
        st.grab = None
        if mode == "select":
            st.sel = self.pick(st, p0, zoom)
        if not st.sel:
            st.msg = "nothing here" if mode == "select" else "select something first (mode 4)"
            return st
        box = st.sel[0] in ("box", "proposal")
        if box and (self._near_corner(st, p0, zoom) if mode == "select" else mode == "resize"):
            return self.act(st, lambda a: self._resize(st.sel, a, p0, p1))
        return self.act(st, lambda a: self._shift(st.sel, a, p1[0] - p0[0], p1[1] - p0[1]))

    def _near_corner(self, st: Session, pt, zoom: float) -> bool:
        """Whether `pt` is within picking distance of a corner of the selected box's rectangle."""
        b = self._selected_item(st)
        if b is None:
            return False
        tol = _pick_tolerance(st.ann, zoom)
        return any(np.hypot(x - pt[0], y - pt[1]) <= tol for x in (b["p0"][0], b["p1"][0]) for y in (b["p0"][1], b["p1"][1]))

    @staticmethod
    def _resize(sel, a, grab, to):
        """Move the corner of the selected box (or proposal) nearest to `grab` to `to`; the
        opposite corner stays."""
        kind, key = sel
        for b in a["boxes"] if kind == "box" else a.get("proposals", []):
            if b["id"] == key:
                for ax in (0, 1):
                    k = "p0" if abs(b["p0"][ax] - grab[ax]) <= abs(b["p1"][ax] - grab[ax]) else "p1"
                    b[k] = list(b[k])
                    b[k][ax] = to[ax]
                return f"{kind} {key} resized"
        return "the selected item is gone"

    @staticmethod
    def _shift(sel, a, dx: float, dy: float):
        """Move the selected item by (dx, dy) photo pixels."""
        kind, key = sel

        def by(p):
            return [round(p[0] + dx, 2), round(p[1] + dy, 2)]
        if kind == "corner" and key < len(a["rack"]["corners"]):
            a["rack"]["corners"][key] = by(a["rack"]["corners"][key])
            return f"corner {key + 1} moved"
        items = {"shelf": a["shelves"], "box": a["boxes"], "proposal": a.get("proposals", [])}.get(kind, [])
        for it in items:
            if it["id"] == key:
                if kind == "shelf":
                    it["point"] = by(it["point"])
                else:
                    it["p0"], it["p1"] = by(it["p0"]), by(it["p1"])
                return f"{kind} {key} moved"
        return "the selected item is gone"

    def _move(self, st: Session, a, pt):
        """Move the selected item to `pt` (a box: its centre)."""
        kind, key = st.sel
        if kind == "corner" and key < len(a["rack"]["corners"]):
            a["rack"]["corners"][key] = pt
            return f"corner {key + 1} moved"
        if kind == "shelf":
            for s in a["shelves"]:
                if s["id"] == key:
                    s["point"] = pt
                    return "shelf moved"
        if kind in ("box", "proposal"):
            for b in a["boxes"] if kind == "box" else a["proposals"]:
                if b["id"] == key:
                    return self._shift(st.sel, a, pt[0] - (b["p0"][0] + b["p1"][0]) / 2,
                                       pt[1] - (b["p0"][1] + b["p1"][1]) / 2)
        return "the selected item is gone"

    def pick(self, st: Session, pt, zoom: float = 1.0) -> list | None:
        """The item under a click: a corner, then the smallest box or proposal containing it,
        then the nearest shelf line (within a 50th of the photo, less when zoomed in)."""
        a = st.ann
        tol = _pick_tolerance(a, zoom)
        for k, q in enumerate(a["rack"]["corners"]):
            if np.hypot(q[0] - pt[0], q[1] - pt[1]) <= tol:
                return ["corner", k]
        scene = self.scene(a)
        best = None
        for kind, items in (("box", a["boxes"]), ("proposal", a.get("proposals", []))):
            for b in items:
                poly = G.box_polygon(scene, b)
                if _inside(poly, pt):
                    area = abs(G.polygon_area(poly))
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

    def delete(self, st: Session) -> Session:
        if not st.sel:
            st.msg = "nothing selected"
            return st
        if st.sel[0] == "proposal":
            return self.reject(st)
        kind, key = st.sel

        def rm(a):
            if kind == "corner":
                if key < len(a["rack"]["corners"]):
                    a["rack"]["corners"].pop(key)
            elif kind == "shelf":
                a["shelves"] = [s for s in a["shelves"] if s["id"] != key]
            elif kind == "box":
                a["boxes"] = [b for b in a["boxes"] if b["id"] != key]
            return f"{kind} {key} deleted"
        st.sel = None
        if kind == "corner":
            st.mode = "corners"
        return self.act(st, rm)

    def set_box_field(self, st: Session, field: str, value) -> Session:
        sel = st.sel
        if not sel or sel[0] not in ("box", "proposal"):
            if value is not None:
                st.msg = "select a box first"
            return st
        if value is not None and (not np.isfinite(value) or value < 0 or (field == "depth" and value == 0)):
            st.msg = f"⚠ {field.replace('_', ' ')} must be a positive number of metres"
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

    def set_rack(self, st: Session, preset_name=None, width=None, height=None, depth=None) -> Session:
        def upd(a):
            r = a["rack"]
            before_rack = dict(r)
            if preset_name is not None:
                p = S.preset(self.project.settings, preset_name)
                if p is None:
                    return f"unknown preset {preset_name!r}"
                r.update(width=p["width"], height=p["height"], depth=p["depth"], preset=p["name"], size_confirmed=True)
                return f"rack preset {p['name']}"
            for k, v in (("width", width), ("height", height), ("depth", depth)):
                if v is not None and v != r.get(k):
                    lo, hi = S.RACK_SIZE_M
                    if not (np.isfinite(v) and lo <= v <= hi):
                        return f"⚠ rack {k} must be between {lo:g} and {hi:g} m"
                    r[k] = float(v)
                    r["preset"] = None
                    r["size_confirmed"] = True
            return f"rack size {r['width']:g} × {r['height']:g} × {r['depth']:g} m" if r != before_rack else ""
        return self.act(st, upd)

    def size_from_box(self, st: Session) -> Session:
        """`g`: the rack's width and height from the selected box, an object of known size on the
        rack's front plane (a pallet, a carton, a beam label): the box spans du × dv of the rack
        plane, so the rack is (ref width / du) × (ref height / dv) times its current size. A
        dimension whose reference is not given stays; the depth stays."""
        sel, ref = st.sel, st.ref
        if st.ann is None:
            return st
        if not sel or sel[0] not in ("box", "proposal"):
            st.msg = "select the box of the reference object first (mode 4), then press g"
            return st
        if not any(ref):
            st.msg = "type the reference object's width and/or height (metres) first"
            return st
        scene = self.scene(st.ann)
        if scene is None:
            st.msg = "mark the rack's 4 corners (and its size, any guess) first"
            return st
        b = self._selected_item(st)
        if b is None:
            st.msg = "the selected item is gone"
            return st
        uv = scene.plane.to_plane([b["p0"], b["p1"]])
        du, dv = abs(uv[1, 0] - uv[0, 0]), abs(uv[1, 1] - uv[0, 1])
        new = {}
        for k, r, d, cur in (("width", ref[0], du, scene.plane.width), ("height", ref[1], dv, scene.plane.height)):
            if r:
                if d < 1e-6:
                    st.msg = f"⚠ the selected box has no {k} on the photo"
                    return st
                new[k] = round(cur * r / d, 3)
        st = self.set_rack(st, **new)
        if st.msg.startswith("⚠"):
            return st
        kept = "; height unchanged (type the reference's height too)" if "height" not in new else (
            "; width unchanged (type the reference's width too)" if "width" not in new else "")
        st.msg = (f"rack size from {sel[0]} {sel[1]} ({_fmt_ref(ref)}): "
                  + " × ".join(f"{k} {v:g} m" for k, v in new.items()) + f"{kept}; depth unchanged")
        return st

    def mark_done(self, st: Session, armed: str | None = None) -> Session:
        """`d`: mark the photo done. While model proposals wait, the first press asks and the
        second (the very next action) rejects them all, then marks done."""
        waiting = len((st.ann or {}).get("proposals") or [])
        if waiting and armed != "reject_proposals":
            st.confirm = "reject_proposals"
            st.msg = (f"⚠ {waiting} model proposal(s) wait: press d again to reject them all and mark done "
                      "(a / A accepts)")
            return st
        if waiting:
            st = self.act(st, lambda a: self._reject_all(a))
        return self.set_status(st, "done")

    def _reject_all(self, a) -> str:
        scene = self.scene(a)
        for p in a.get("proposals", []):
            self._remember_rejected(a, scene, p)
        n = len(a.get("proposals", []))
        a["proposals"] = []
        return f"{n} proposal(s) rejected"

    @staticmethod
    def _remember_rejected(a, scene, p) -> None:
        """Record a rejected proposal's metric rectangle: it is not proposed again."""
        if scene is None:
            return
        mb = G.metric_box(scene.plane, p, scene.shelf_v, scene.depth, scene.depth)
        if mb.shelf is not None:
            a.setdefault("rejected", []).append([mb.shelf, round(mb.u0, 4), round(mb.u1, 4), round(mb.v0, 4), round(mb.v1, 4)])

    def set_status(self, st: Session, status: str) -> Session:
        """Set the photo's status; `done` and `approved` are refused (one line saying what to
        fix) while done_problems() finds anything."""
        if status not in S.STATUSES:
            st.msg = f"unknown status {status!r}"
            return st
        if status in DONE_STATUSES and st.ann is not None:
            probs = self.done_problems(st.ann)
            if probs:
                more = f" (and {len(probs) - 1} more, see the summary)" if len(probs) > 1 else ""
                st.msg = f"⚠ not marked {status}: {probs[0]}{more}; your work is saved"
                return st

        def upd(a):
            a["status"] = status
            return f"status: {status}"
        return self.act(st, upd)

    def done_problems(self, a: S.Annotation) -> list[str]:
        """What stops this annotation from being `done`: missing corners, rack size or shelves,
        a rack size nobody confirmed (the default preset the first corner applied), waiting
        model proposals, and every geometry warning (annotate.geometry)."""
        out = []
        r = a["rack"]
        if len(r["corners"]) < 4:
            out.append(f"only {len(r['corners'])} of 4 rack corners set")
        if r["width"] is None or r["height"] is None or r["depth"] is None:
            out.append("the rack size is not set: pick a preset or type width, height and depth")
        elif r.get("size_confirmed") is False:
            out.append(f"the rack size {r['width']:g} × {r['height']:g} × {r['depth']:g} m is the default preset, "
                       "not confirmed: type the size, pick a preset, or press c (confirm size)")
        if not a["shelves"]:
            out.append("no shelf marked (mode 2)")
        if a.get("proposals"):
            out.append(f"{len(a['proposals'])} model proposal(s) wait: accept (a) or reject (r) them")
        R = self.project.settings["R"]
        if len(a["shelves"]) > R:
            out.append(f"{len(a['shelves'])} shelves marked but the project has R={R} channels")
        if len(r["corners"]) == 4 and r["width"] and r["height"] and r["depth"]:
            d = self._derive(a)
            out += d.scene.warnings if d.scene is not None else [d.error]
        return out

    def confirm_size(self, st: Session) -> Session:
        def upd(a):
            r = a["rack"]
            if r["width"] is None:
                return "no rack size to confirm yet: click a corner or pick a preset"
            r["size_confirmed"] = True
            return f"rack size {r['width']:g} × {r['height']:g} × {r['depth']:g} m confirmed"
        return self.act(st, upd)

    def split_row(self, st: Session) -> Session:
        """`w`: the selected box drawn around a row of N equal loads (N typed under Selection)
        becomes N boxes of equal width along the rack, split in metres on the rack plane (so a
        row seen at an angle is split where its loads are, not at equal pixels). Each keeps the
        box's depth, front offset, on-board flag and source."""
        row = self._selected_row(st, "w")
        if row is None:
            return st
        b, scene, (u0, u1, v0, v1) = row
        cuts = np.linspace(u0, u1, int(st.split_n) + 1)
        return self._replace_box(st, b, scene, list(zip(cuts[:-1], cuts[1:])), v0, v1, "")

    def split_at_gaps(self, st: Session) -> Session:
        """`W`: the selected box drawn around a row of loads is cut where the photo shows a gap
        between them (a narrow dark slot along it, `geometry.split_at_dark_gaps`: the same cut as
        the model proposals'), however many loads and whatever their widths. Each part keeps the
        box's heights, depth, front offset, on-board flag and source."""
        row = self._selected_row(st, "W")
        if row is None:
            return st
        b, scene, (u0, u1, v0, v1) = row
        parts = G.split_at_dark_gaps(G.Proposal(0, u0, u1, v0, v1, None, 0.0), self.luma(st.name), scene.plane,
                                     self.gap_split)
        if len(parts) < 2:
            st.msg = (f"no gap between loads shows along box {b['id']} in the photo: split it into N equal "
                      f"boxes (w) or draw the loads one by one")
            return st
        return self._replace_box(st, b, scene, [(p.u0, p.u1) for p in parts], v0, v1, " at the photo's gaps")

    def _selected_row(self, st: Session, key: str):
        """(box, scene, (u0, u1, v0, v1) on the rack plane) of the selected box, or None with the
        reason in st.msg."""
        b = self._selected_box(st)
        if b is None:
            st.msg = (f"accept the proposal first (a), then press {key}" if st.sel and st.sel[0] == "proposal"
                      else "select the box drawn around the row first (mode 4)")
            return None
        scene = self.scene(st.ann)
        if scene is None:
            st.msg = "mark the rack's 4 corners and its size first"
            return None
        uv = scene.plane.to_plane([b["p0"], b["p1"]])
        (u0, u1), (v0, v1) = sorted(uv[:, 0]), sorted(uv[:, 1])
        return b, scene, (float(u0), float(u1), float(v0), float(v1))

    def _replace_box(self, st: Session, b: dict, scene, spans, v0: float, v1: float, how: str) -> Session:
        """Box `b` replaced by one box per (u0, u1) of `spans` from v0 to v1 (rack plane), each with
        b's other fields; the first selected."""
        def upd(a):
            keep = {k: v for k, v in b.items() if k not in ("id", "p0", "p1")}
            a["boxes"] = [x for x in a["boxes"] if x["id"] != b["id"]]
            made = []
            for s0, s1 in spans:
                p = scene.plane.to_image([[s0, v0], [s1, v1]])
                nb = dict(keep, id=_next_id(a["boxes"]), p0=[round(float(c), 2) for c in p[0]],
                          p1=[round(float(c), 2) for c in p[1]])
                a["boxes"].append(nb)
                made.append(nb["id"])
            st.sel = ["box", made[0]]
            return f"box {b['id']} split{how} into {len(made)} boxes ({', '.join(map(str, made))}); box {made[0]} selected"
        return self.act(st, upd)

    def toggle_on_board(self, st: Session) -> Session:
        b = self._selected_box(st)
        if b is None:
            st.msg = "select a box first (mode 4)"
            return st

        def upd(a):
            for x in a["boxes"]:
                if x["id"] == b["id"]:
                    if x.get("on_board", True):
                        x["on_board"] = False
                        return f"box {b['id']} floats: its bottom is where you clicked (on something)"
                    x.pop("on_board", None)
                    return f"box {b['id']} stands on its board"
        return self.act(st, upd)

    def set_field(self, st: Session, field: str, text) -> Session:
        """A number typed into a field, applied exactly as typed (`text` is the field's text)."""
        text = "" if text is None else str(text).strip()
        if text == "":
            value = None
        else:
            try:
                value = float(text)
            except ValueError:
                st.msg = f"⚠ {field.replace('_', ' ')}: {text!r} is not a number"
                return st
            if not math.isfinite(value):
                st.msg = f"⚠ {field.replace('_', ' ')}: {text!r} is not a finite number"
                return st
        if field in ("width", "height", "depth"):
            if value is None:
                st.msg = f"⚠ rack {field} cannot be empty"
                return st
            return self.set_rack(st, **{field: value})
        if field in ("box_depth", "box_offset"):
            return self.set_box_field(st, "depth" if field == "box_depth" else "front_offset", value)
        if field == "split_n":
            if value is None or value != int(value) or not 2 <= value <= 50:
                st.msg = "⚠ split into: a whole number of boxes from 2 to 50"
                return st
            st.split_n = int(value)
            st.msg = f"w splits the selected box into {st.split_n} equal boxes"
            return st
        if field in ("ref_width", "ref_height"):
            if value is not None and not 0 < value <= 100:
                st.msg = f"⚠ reference {field[4:]} must be between 0 and 100 m"
                return st
            st.ref = list(st.ref)
            st.ref[0 if field == "ref_width" else 1] = value
            st.msg = (f"reference object {_fmt_ref(st.ref)}: select its box and press g (rack size from it)"
                      if any(st.ref) else "no reference object")
            return st
        raise ValueError(f"unknown field {field!r}")

    # --- proposals ---------------------------------------------------------------------------
    def prediction(self, name: str, corners=None) -> dict:
        """The model's prediction for a photo; with the rack's corners (stored pixels, as the
        annotation keeps them) it reads the photo cropped to the outlined rack (`racklay predict
        --rack-box`: on photos of sites no model saw, 3-5 box-IoU points more than the whole frame,
        docs/eval-predict.md), else the whole photo."""
        with self._lock:
            key = (name, None if corners is None else tuple(map(tuple, np.round(np.asarray(corners, float), 1))))
            if key not in self._preds:
                # the model sees the photo as taken (a squeezed photo un-squeezed); its layouts are
                # metric and reach the photo through the rack plane, whatever the pixel aspect
                image = self.image(name)
                rgb = G.restore_aspect(image, S.pixel_aspect(self.project.settings))
                box = None
                if corners is not None:
                    c = np.asarray(corners, float) * [rgb.shape[1] / image.shape[1], 1.0]
                    box = (*c.min(0), *c.max(0))
                try:
                    self._preds[key] = self.predictor.predict(rgb, rack_box=box, source=name)
                except ValueError:      # corners that miss the photo: read the whole of it
                    self._preds[key] = self.predictor.predict(rgb, source=name)
                while len(self._preds) > 8:
                    self._preds.popitem(last=False)
            return self._preds[key]

    def luma(self, name: str) -> np.ndarray:
        """The photo's luminance (uint8, H x W) in its stored pixels, where the rack plane (the
        labeller's corners) lives, also for a squeezed photo: what the gap cuts read."""
        with self._lock:
            if name not in self._luma:
                self._luma[name] = np.clip(luminance(self.image(name)) + 0.5, 0, 255).astype(np.uint8)
                while len(self._luma) > 8:
                    self._luma.popitem(last=False)
            self._luma.move_to_end(name)
            return self._luma[name]

    def refresh_proposals(self, ann: S.Annotation) -> str:
        """Recompute the model's box proposals for the current corners and shelves (skipping
        those that overlap a box already there or one the labeller rejected): the stacks the rack
        reasoning reads in the model's layouts, each cut where the photo shows a gap along it
        (`gap_split`, geometry.split_at_dark_gaps)."""
        scene = self.scene(ann)
        if scene is None:
            ann["proposals"] = []
            return ""
        pred = self.prediction(ann["image"], ann["rack"]["corners"] if self.read_rack_crop else None)
        if "front" not in pred:
            return "model has no front view: no proposals"
        if not scene.shelf_v:
            n = int(sum((pred["front"][i] == L.BOX).any() for i in range(pred["front"].shape[0])))
            ann["proposals"] = []
            return f"model ready ({n} shelf channel(s) with boxes): mark the shelves to see its box proposals"
        # the labeller's rack width is the shelves' known length: it fixes the model's scale, so
        # proposals keep the predicted shape and land where the rack is (racklay.predict.with_shelf_length)
        from racklay.predict import with_shelf_length

        try:
            pred = with_shelf_length(pred, scene.width)
        except ValueError as e:          # a rack wider than the layout grid
            ann["proposals"] = []
            return f"no model proposals: {e}"
        probs = pred.get("probs", {}).get("front")

        def read(front, top):
            return G.front_box_rects(front, top, pred["grid"], scene.shelf_v, scene.width, scene.depth,
                                     probs_box=None if probs is None else probs[:, L.BOX],
                                     tops=[v + c for v, c in zip(scene.shelf_v, scene.clear)], cfg=self.reasoning)

        props = read(pred["front"], pred.get("top"))
        gaps = G.photo_gaps(props, self.luma(ann["image"]), scene.plane, self.gap_split) if self.gap_split.depth else []
        if gaps:     # one proposal per load: the layouts cut where the photo shows a gap, read again
            props = read(*(None if v is None else G.cut_box_columns(v, pred["grid"], scene.width, gaps)
                           for v in (pred["front"], pred.get("top"))))
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

    def accept(self, st: Session, all_: bool = False) -> Session:
        sel = st.sel
        if not all_ and (not sel or sel[0] != "proposal"):
            st.msg = "select a proposal first (mode 4)"
            return st

        def upd(a):
            take = [p for p in a.get("proposals", []) if all_ or p["id"] == sel[1]]
            for p in take:
                b = dict(p, id=_next_id(a["boxes"]), source="model")
                a["boxes"].append(b)
            a["proposals"] = [p for p in a.get("proposals", []) if p not in take]
            # one accepted proposal stays selected, as the box it became, ready to be edited
            st.sel = ["box", a["boxes"][-1]["id"]] if len(take) == 1 and not all_ else None
            return f"accepted {len(take)} proposal(s)" + (f": box {st.sel[1]} selected" if st.sel else "")
        st.sel = None
        return self.act(st, upd)

    def reject(self, st: Session) -> Session:
        sel = st.sel
        if not sel or sel[0] != "proposal":
            st.msg = "select a proposal first (mode 4)"
            return st

        def upd(a):
            scene = self.scene(a)
            for p in a.get("proposals", []):
                if p["id"] == sel[1]:
                    self._remember_rejected(a, scene, p)
                    a["proposals"] = [q for q in a["proposals"] if q["id"] != sel[1]]
                    return "proposal rejected"
        st.sel = None
        return self.act(st, upd)

    # --- the geometry of an annotation, built once ---------------------------------------------
    def _derive(self, ann: S.Annotation) -> _Derived:
        """The scene of `ann`'s rack, shelves and boxes under the project settings: built the
        first time they are seen and kept for the last few (an event's edit, outlines, texts and
        preview all use the same one; status, proposals and versions do not change it)."""
        key = json.dumps([ann["rack"], ann["shelves"], ann["boxes"], self.project.settings],
                         sort_keys=True, default=str)
        with self._lock:
            hit = self._derived.get(key)
            if hit is not None:
                self._derived.move_to_end(key)
                return hit
        try:
            d = _Derived(G.build_scene(ann, self.project.settings))
        except (G.GeometryError, ValueError) as e:
            d = _Derived(None, str(e))
        with self._lock:
            self._derived[key] = d
            while len(self._derived) > 8:
                self._derived.popitem(last=False)
        return d

    def scene(self, ann: S.Annotation) -> G.Scene | None:
        """The annotation's metric scene, or None while it does not define a rack."""
        return self._derive(ann).scene

    def layouts(self, ann: S.Annotation):
        """(scene, top, front) of an annotation; top and front are None without a shelf or when
        there are more shelves than the project's R."""
        d = self._derive(ann)
        if d.layouts is None:
            out = (d.scene, None, None)
            if d.scene is not None and d.scene.shelf_v:
                cfg = self.project.settings
                try:
                    top, front = d.scene.layouts(cfg["R"], L.Grid(cfg["D"], cfg["extent"]))
                    out = (d.scene, top, front)
                except G.GeometryError:
                    pass
            d.layouts = out
        return d.layouts

    def frame(self, st: Session) -> D.Frame:
        """What the page shows for this session, for annotate.draw."""
        if st.ann is None:
            return D.Frame(st, self.project)
        return D.Frame(st, self.project, *self.layouts(st.ann))


def _pick_tolerance(a: S.Annotation, zoom: float) -> float:
    """How near (photo pixels) a click must be to pick a point or line: a 50th of the photo, less
    when zoomed in."""
    W, H = a["image_size"]
    return max(W, H) / 50 / max(1.0, float(zoom or 1.0))


def _fmt_ref(ref) -> str:
    w, h = ref
    return " × ".join(x for x in (f"{w:g} m wide" if w else "", f"{h:g} m high" if h else "") if x)


def _finite(v) -> float:
    """A number from the page: finite, or ValueError."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"expected a finite number, got {v!r}")
    return float(v)


def _content(a: dict) -> dict:
    return {k: v for k, v in a.items() if k not in ("version", "updated_at", "updated_by")}


def _next_id(items) -> int:
    return max((int(i["id"]) for i in items), default=-1) + 1


def _inside(poly, pt) -> bool:
    import cv2

    return cv2.pointPolygonTest(np.asarray(poly, np.float32), (float(pt[0]), float(pt[1])), False) >= 0


def _seg_dist(seg, pt) -> float:
    a, b, p = np.asarray(seg[0], float), np.asarray(seg[1], float), np.asarray(pt, float)
    d = b - a
    t = np.clip(np.dot(p - a, d) / max(np.dot(d, d), 1e-12), 0, 1)
    return float(np.linalg.norm(a + t * d - p))

