"""Actions per photo: the per-box labelling flow against the row tool, on the same labelled photos.

    .venv/bin/python -m bench.speed.labelling_actions [--project datasets/real-photos] [--photos 01_,03_,...]

Each photo's existing labels are replayed through the annotation tool's own action handler
(`annotate.editor.Tool.apply`, what the page sends), twice, into scratch copies of the project:

* **per box** (the flow before the row tool): 4 corners, the rack size typed (3 numbers) and
  confirmed, one click per shelf, then two clicks per box plus its typed depth / offset and `f`
  where its labels have them, `d`;
* **rows**: the same, but every run of equal loads side by side on one board (same bottom and
  top within 5 cm and 8 %, widths within 20 %, at most 5 cm apart, same depth / offset / flag)
  is drawn once around the whole row, N typed under Selection and `w` pressed
  (`Tool.split_row`: N boxes of equal width on the rack plane).

It prints the actions of each flow (clicks on the photo, keys, typed numbers), a labeller's input
time from them (1.5 s a click, 1 s a key, 4 s a typed number: docs/annotate.md; the time spent
deciding what to click comes on top and is not measured here), and how close the row flow's
layouts are to the per-box ones (box IoU, top / front): the row tool saves actions only where
the loads really are equal. Sizing the rack from a reference object (`g`) saves judgement, not
actions, so both flows type the rack size.
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from bench.common import REPO

CLICK_S, KEY_S, NUMBER_S = 1.5, 1.0, 4.0
DEFAULT_PHOTOS = ("01_blueshelf_lux", "03_blueshelf_cartons2", "04_blueshelf_surf", "05_blueshelf_tulip",
                  "15_loco_red_racks_jacks")


class Replay:
    """Sends actions to a Tool session and counts them as a labeller's clicks, keys and numbers."""

    def __init__(self, tool, name: str):
        self.tool, self.st = tool, tool.open(name)
        self.clicks = self.keys = self.numbers = 0
        self.seq = 0

    def send(self, action: dict, kind: str) -> None:
        self.seq += 1
        self.st = self.tool.apply(self.st, [dict(action, seq=self.seq, image=self.st.name)])
        if self.st.msg.startswith("⚠"):
            raise SystemExit(f"{self.st.name}: the tool refused {action}: {self.st.msg}")
        setattr(self, kind, getattr(self, kind) + 1)

    def mode(self, m):
        self.send({"kind": "mode", "mode": m}, "keys")

    def click(self, pt):
        self.send({"kind": "click", "x": pt[0], "y": pt[1]}, "clicks")

    def box(self, p0, p1):
        self.send({"kind": "box", "p0": list(p0), "p1": list(p1)}, "clicks")
        self.clicks += 1                                  # two clicks (or one drag) per box

    def number(self, field, value):
        self.send({"kind": "field", "field": field, "text": str(value)}, "numbers")

    def key(self, name):
        self.send({"kind": "act", "name": name}, "keys")

    def seconds(self) -> float:
        return CLICK_S * self.clicks + KEY_S * self.keys + NUMBER_S * self.numbers


def rack_and_shelves(c: Replay, ann: dict) -> None:
    rack = ann["rack"]
    c.mode("corners")
    for pt in rack["corners"]:
        c.click(pt)
    for f in ("width", "height", "depth"):
        c.number(f, rack[f])
    c.key("confirm_size")
    c.mode("shelves")
    for s in ann["shelves"]:
        c.click(s["point"])
    c.mode("boxes")


def box_extras(c: Replay, b: dict) -> None:
    """What a labeller sets on the box just drawn (it is selected): depth, front offset, `f`."""
    if b.get("depth") is not None:
        c.number("box_depth", b["depth"])
    if b.get("front_offset") is not None:
        c.number("box_offset", b["front_offset"])
    if b.get("on_board") is False:
        c.key("toggle_on_board")


def rows(boxes: list[dict], plane) -> list[list[dict]]:
    """The labels' boxes grouped into runs of equal loads side by side (each group >= 1 box),
    measured in metres on the rack plane."""
    def uv(b):
        p = plane.to_plane([b["p0"], b["p1"]])
        (u0, u1), (v0, v1) = sorted(p[:, 0]), sorted(p[:, 1])
        return u0, u1, v0, v1

    def key(b):
        return b.get("depth"), b.get("front_offset"), b.get("on_board", True)

    items = sorted(((uv(b), b) for b in boxes), key=lambda t: (round(t[0][2], 1), t[0][0]))
    groups: list[list] = []
    for m, b in items:
        g = groups[-1] if groups else None
        if g is not None:
            (u0, u1, v0, v1), last = g[-1]
            w, wl, h = m[1] - m[0], u1 - u0, v1 - v0
            if (abs(m[2] - v0) <= 0.05 and abs((m[3] - m[2]) - h) <= 0.08 * h and abs(w - wl) <= 0.2 * wl
                    and -0.05 <= m[0] - u1 <= 0.05 and key(b) == key(last)):
                g.append((m, b))
                continue
        groups.append([(m, b)])
    return [[b for _, b in g] for g in groups]


def flow(tool, name: str, ann: dict, by_rows: bool) -> tuple[Replay, int]:
    """One photo labelled again from its labels, box by box or by rows: (the replay, how many
    boxes or rows were drawn)."""
    c = Replay(tool, name)
    rack_and_shelves(c, ann)
    groups = rows(ann["boxes"], tool.scene(c.st.ann).plane) if by_rows else [[b] for b in ann["boxes"]]
    for g in groups:
        if len(g) == 1:
            c.box(g[0]["p0"], g[0]["p1"])
            box_extras(c, g[0])
            continue
        pts = np.array([p for b in g for p in (b["p0"], b["p1"])], float)
        lo, hi = pts.min(0), pts.max(0)
        c.box([lo[0], hi[1]], [hi[0], lo[1]])
        box_extras(c, g[0])
        c.number("split_n", len(g))
        c.key("split_row")
    c.key("done")
    return c, len(groups)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--project", type=Path, default=REPO / "datasets" / "real-photos",
                    help="annotate project whose labels are replayed (default datasets/real-photos)")
    ap.add_argument("--photos", default=",".join(DEFAULT_PHOTOS),
                    help="comma-separated photo names or name prefixes (default: 5 photos of the set)")
    args = ap.parse_args()

    from annotate.editor import Tool
    from annotate.store import Project
    from racklay.metrics import confusion, confusion_scores

    def box_iou(a, b) -> float:
        return 100 * confusion_scores(confusion(np.asarray(a), np.asarray(b)))["box"]["IoU"]

    src = Project(args.project)
    names = [n for p in args.photos.split(",") for n in src.images() if n.startswith(p)]
    if not names:
        raise SystemExit(f"{args.project}: no photo matches {args.photos!r}")
    tmp = Path(tempfile.mkdtemp(prefix="labelling-actions-"))
    print("| photo | boxes | drawings the rows save | per box: clicks / keys / numbers | rows: clicks / keys / numbers "
          "| input s per box | input s rows | ratio | rows vs per box: box IoU top / front |")
    print("|---|---|---|---|---|---|---|---|---|")
    tot = [0.0, 0.0]
    try:
        for k, name in enumerate(names):
            ann = src.load(name)
            made = {}
            for by_rows in (False, True):
                proj = tmp / f"{'rows' if by_rows else 'boxes'}-{k}"
                proj.mkdir()
                shutil.copy(args.project / "project.json", proj / "project.json")
                shutil.copy(args.project / name, proj / name)
                tool = Tool(Project(proj))
                c, drawn = flow(tool, name, ann, by_rows)
                tool.flush_history()
                _, top, front = tool.layouts(c.st.ann)
                made[by_rows] = (c, top, front, drawn)
            (a, ta, fa, _), (b, tb, fb, nrows) = made[False], made[True]
            tot[0] += a.seconds()
            tot[1] += b.seconds()
            print(f"| {name} | {len(ann['boxes'])} | {len(ann['boxes']) - nrows} "
                  f"| {a.clicks} / {a.keys} / {a.numbers} | {b.clicks} / {b.keys} / {b.numbers} | {a.seconds():.0f} "
                  f"| {b.seconds():.0f} | {b.seconds() / a.seconds():.2f} | {box_iou(ta, tb):.1f} / {box_iou(fa, fb):.1f} |")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nall {len(names)} photos: input {tot[0]:.0f} s per box, {tot[1]:.0f} s with rows "
          f"({tot[1] / tot[0]:.2f}x; target: half of today's time per photo, which also counts deciding "
          f"what to click, not measured here)")
    print(json.dumps({"per_box_s": round(tot[0], 1), "rows_s": round(tot[1], 1)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
