"""What the annotation tool shows, drawn from a Frame: the outlines over the photo (as shapes the
page draws), the live layouts preview, the summary, header and selection texts, and the photo
as the browser gets it. No logic and no file access here: annotate.editor.Tool gathers a Frame
once per event (the annotation's scene and layouts built once, shared by everything below).
"""
from __future__ import annotations

import base64
import html
import re
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from racklay import layout as L
from racklay.viz import PALETTE, colorize, content_window

from . import geometry as G
from .session import Session
from .store import DONE_STATUSES, Project

# overlay colours
C_RACK, C_SHELF, C_BOX, C_FLOAT = (255, 220, 0), (0, 220, 255), tuple(int(v) for v in PALETTE[L.BOX]), (255, 60, 60)
C_PROP, C_SEL, C_PEND, C_IMPORT = (60, 240, 90), (255, 255, 255), (255, 0, 255), (190, 120, 255)
#: the longest side of the photo as sent to the browser (larger photos are shown scaled down;
#: clicks are still in the photo's own pixels)
VIEW_MAX_SIDE = 4096


@dataclass
class Frame:
    """Everything one answer to the page is drawn from. `scene` is the open annotation's metric
    scene (None without 4 corners and a rack size, or when they do not define a rack), `top` and
    `front` its layouts (None without a shelf). The project's statuses and the imported layouts
    are read when first needed, at most once per frame."""

    st: Session
    project: Project
    scene: G.Scene | None = None
    top: np.ndarray | None = None
    front: np.ndarray | None = None

    @property
    def settings(self):
        return self.project.settings

    @cached_property
    def statuses(self) -> dict[str, str]:
        return self.project.statuses()

    @cached_property
    def imported(self) -> dict[str, np.ndarray]:
        a = self.st.ann
        return self.project.read_imported(a) if a is not None and a.get("imported") else {}


def hex_colour(c) -> str:
    return "#%02x%02x%02x" % tuple(int(v) for v in c)


def overlay(f: Frame) -> list[dict]:
    """Everything drawn over the photo, as shapes in photo pixels for the page to draw: the
    rack outline and corners, shelf lines, boxes (red: on no shelf), proposals, imported
    boxes, the half-drawn box's first corner. Outline widths are screen pixels."""
    st, a, scene = f.st, f.st.ann, f.scene
    if a is None:
        return []
    out: list[dict] = []

    def poly(pts, c, w=1.5, closed=True):
        out.append({"t": "poly", "pts": [[round(float(x), 2), round(float(y), 2)] for x, y in np.asarray(pts).reshape(-1, 2)],
                    "c": hex_colour(c), "w": w, "closed": closed})

    sel = st.sel or [None, None]
    corners = a["rack"]["corners"]
    if len(corners) == 4:
        poly(G.order_corners(corners), C_RACK, 2)
    for k, q in enumerate(corners):
        out.append({"t": "dot", "x": q[0], "y": q[1], "r": 6 if sel == ["corner", k] else 4,
                    "c": hex_colour(C_SEL if sel == ["corner", k] else C_RACK)})
    if scene is not None:
        for k, (sid, v) in enumerate(zip(scene.shelf_ids, scene.shelf_v)):
            seg = G.shelf_line(scene.plane, v)
            chosen = sel == ["shelf", sid]
            poly(seg, C_SEL if chosen else C_SHELF, 3 if chosen else 1.5, closed=False)
            out.append({"t": "text", "x": round(float(seg[0][0]) + 4, 1), "y": round(float(seg[0][1]) - 4, 1),
                        "s": f"S{k + 1}", "c": hex_colour(C_SHELF)})
        imp = f.imported
        if "front" in imp and scene.shelf_v:
            grid = L.Grid(imp["front"].shape[-1], f.settings["extent"])
            for p in G.front_box_rects(imp["front"], imp.get("top"), grid, scene.shelf_v, scene.width, scene.depth):
                poly(G.rect_outline(scene.plane, p.u0, p.u1, p.v0, p.v1), C_IMPORT, 1)
    else:
        for s in a["shelves"]:
            out.append({"t": "cross", "x": s["point"][0], "y": s["point"][1], "c": hex_colour(C_SHELF)})
    metric = {m.id: m for m in scene.boxes} if scene is not None and scene.shelf_v else {}
    for kind, items, col in (("proposal", a.get("proposals", []), C_PROP), ("box", a["boxes"], C_BOX)):
        for b in items:
            polyg = G.box_polygon(scene, b)
            colour = col
            if kind == "box" and b["id"] in metric and metric[b["id"]].shelf is None:
                colour = C_FLOAT
            chosen = sel == [kind, b["id"]]
            poly(polyg, C_SEL if chosen else colour, 3 if chosen else 1.5)
            if kind == "proposal":
                out.append({"t": "text", "x": float(polyg[3][0]), "y": float(polyg[3][1]), "s": "?", "c": hex_colour(C_PROP)})
    if st.pending:
        out.append({"t": "cross", "x": st.pending[0], "y": st.pending[1], "c": hex_colour(C_PEND), "r": 8})
    return out


def preview(f: Frame, tile: int = 150) -> np.ndarray | None:
    """Every shelf's top (upper row) and front (lower row) layout, colourised, lowest shelf
    on the left; imported layouts (read-only) in two more rows when the image has them."""
    import cv2

    if f.st.ann is None:
        return None
    rows = []
    if f.top is not None:
        rows += [("top", f.top), ("front", f.front)]
    imp = f.imported
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


def preview_url(f: Frame) -> str | None:
    """The preview as a PNG data URL (None when there is nothing to show)."""
    import cv2

    pv = preview(f)
    if pv is None:
        return None
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(pv[:, :, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def summary(f: Frame) -> str:
    """The rack, every shelf's board and clear height and boxes, and the warnings (markdown)."""
    a, scene, top, front = f.st.ann, f.scene, f.top, f.front
    if a is None:
        return ""
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
    R = f.settings["R"]
    if len(a["shelves"]) > R:
        lines.append(f"- ⚠ {len(a['shelves'])} shelves marked but the project has R={R} channels: "
                     f"delete {len(a['shelves']) - R} (the export refuses this image)")
    if a.get("proposals"):
        lines.append(f"- {len(a['proposals'])} model proposal(s) waiting (green)")
    return "\n".join(lines)


def header(f: Frame) -> str:
    """Progress, the photo's place in the list, its status and the mode (markdown)."""
    st, stats = f.st, f.statuses
    done = sum(v in DONE_STATUSES for v in stats.values())
    bad = sum(v == "unreadable" for v in stats.values())
    names, n = list(stats), len(stats)
    k = names.index(st.name) + 1 if st.name in names else 0
    status = st.ann["status"] if st.ann else stats.get(st.name, "—")
    unread = f" · {bad} unreadable (skipped)" if bad else ""
    return (f"**{done} of {n} done**{unread} · image {k}/{n}: `{st.name}` · status **{status}** · "
            f"mode **{st.mode}**")


def selection(f: Frame) -> tuple[str, float | None, float | None]:
    """The selected item in words, and the selected box's depth and front offset (the number
    fields show them)."""
    sel, a, scene = f.st.sel, f.st.ann, f.scene
    if not sel or a is None:
        return "nothing selected", None, None
    kind, key = sel
    if kind in ("box", "proposal"):
        for b in a["boxes"] if kind == "box" else a.get("proposals", []):
            if b["id"] == key:
                txt = f"{kind} {key} ({b.get('source', 'manual')})"
                if scene is not None:
                    mb = G.metric_box(scene.plane, b, scene.shelf_v, scene.depth, scene.depth)
                    where = f"shelf S{mb.shelf + 1}" if mb.shelf is not None else "no shelf"
                    x0, x1 = L.u_to_x(mb.u0, scene.width), L.u_to_x(mb.u1, scene.width)
                    txt += f": x {x0:+.2f}…{x1:+.2f} m, height {mb.v1 - mb.v0:.2f} m, on {where}"
                return txt, b.get("depth"), b.get("front_offset", 0.0)
    return f"{kind} {key + 1 if kind == 'corner' else key}", None, None


def photo_jpeg_b64(img: np.ndarray) -> str:
    """The photo as the browser shows it: base64 JPEG (quality 92, 4:4:4 chroma), at most
    VIEW_MAX_SIDE pixels a side (the outlines are drawn by the page)."""
    import cv2

    h, w = img.shape[:2]
    k = VIEW_MAX_SIDE / max(h, w)
    if k < 1:
        img = cv2.resize(img, (max(1, int(w * k)), max(1, int(h * k))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img[:, :, ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, 92, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                            cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
    return base64.b64encode(buf.tobytes()).decode("ascii")


def md_html(text: str) -> str:
    """The little markdown the tool's texts use (**bold**, `code`, '- ' list lines) as HTML,
    everything else escaped; drawn by the page (no markdown renderer on every click)."""
    out, items = [], []
    for line in (text or "").split("\n"):
        h = html.escape(line)
        h = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", h)
        h = re.sub(r"`(.+?)`", r"<code>\1</code>", h)
        if h.startswith("- "):
            items.append(f"<li>{h[2:]}</li>")
            continue
        if items:
            out.append("<ul>" + "".join(items) + "</ul>")
            items = []
        if h:
            out.append(f"<p>{h}</p>")
    if items:
        out.append("<ul>" + "".join(items) + "</ul>")
    return "".join(out)


def pre(text: str, **attrs) -> str:
    """`text` in a <pre> element (escaped): how the page receives its data."""
    a = "".join(f' {k.replace("_", "-")}="{html.escape(str(v))}"' for k, v in attrs.items())
    return f"<pre{a}>{html.escape(text)}</pre>"
