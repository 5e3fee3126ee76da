"""How many of the annotator's model proposals a labeller can accept, on labelled photos.

    .venv/bin/python -m bench.accuracy.proposal_quality [--project datasets/real-photos] [--split test]
        [--weights FILE] [--split-step 0 --split-step 0.08]

For every labelled photo, the labeller's own rack (corners, size) and shelves are given to the
annotation tool with no boxes, and the tool proposes boxes exactly as it does in the browser
(`annotate.editor.Tool.refresh_proposals`: the model run on the photo as taken, its layouts scaled
to the typed rack width, read into one rectangle per box stack by `racklay.reasoning`, each cut
where the photo shows a gap along it, `annotate.geometry.split_at_dark_gaps`). The
proposals are matched one to one (greedy, highest IoU first) with the labels' box stacks (labelled
boxes whose footprints overlap, as `racklay.reasoning.group_stacks` groups them; one rectangle
around each stack on the rack plane) on the same shelf: a proposal with IoU >= --iou is one a
labeller accepts as it is.

Prints, per reasoning setting (`--split-step`, repeatable; 0: regions split only at gaps, as before
the step cut), gap cut (`--gap-depth`, repeatable; 0: no cut at the photo's gaps, as before
it) and load width (`--load-width`, repeatable; 0, the default: not known): label stacks, proposals, accepted (IoU >= --iou), precision, recall, the mean IoU of
the accepted, and the labeller's input for the boxes alone: with no model, two clicks per stack;
with proposals, one key per accepted proposal, two clicks per stack left to draw and two keys on
each photo where proposals are left over (`d` rejects the waiting ones after asking once); 1.5 s
a click, 1 s a key, as in bench/speed/labelling_actions.py.

Then, without the model, the row tools: one box drawn around all the labelled stacks of each
shelf, split into N equal boxes (`w`, N the shelf's stack count, typed) or where the photo shows
gaps (`W`, `annotate.editor.Tool.split_at_gaps`): how many label stacks a part matches (IoU >=
--iou) and the input for the boxes (two clicks and a key per shelf, a typed number for `w`, two
clicks for each stack left to draw). Asserts nothing.
"""
from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

from bench.common import REPO, labelled_photos
from bench.speed.labelling_actions import CLICK_S, KEY_S, NUMBER_S
from racklay.predict import add_precision_args


def label_stacks(scene) -> list[tuple[int, tuple[float, float, float, float]]]:
    """(shelf, (u0, u1, v0, v1)) around each labelled box stack, on the rack plane."""
    from racklay.reasoning import group_stacks

    out = []
    for i in range(len(scene.shelf_v)):
        boxes = [b for b in scene.boxes if b.shelf == i]
        for group in group_stacks(scene.layout_boxes(i)):
            bs = [boxes[k] for k in group]
            out.append((i, (min(b.u0 for b in bs), max(b.u1 for b in bs), min(b.v0 for b in bs),
                            max(b.v1 for b in bs))))
    return out


def tool_proposals(tool, ann, scene) -> list[tuple[int, tuple[float, float, float, float]]]:
    """(shelf, (u0, u1, v0, v1)) of the proposals the tool makes for annotation `ann` given its
    rack and shelves but none of its boxes (as a labeller starting the photo sees them)."""
    from annotate.geometry import metric_box

    bare = copy.deepcopy(ann)
    bare["boxes"], bare["proposals"], bare["rejected"] = [], [], []
    tool.refresh_proposals(bare)
    boxes = (metric_box(scene.plane, b, scene.shelf_v, scene.depth, scene.depth) for b in bare["proposals"])
    return [(m.shelf, (m.u0, m.u1, m.v0, m.v1)) for m in boxes if m.shelf is not None]


def match(props, truth, iou_min: float) -> list[float]:
    """IoUs of the one-to-one matches with IoU >= iou_min (greedy, highest first, same shelf)."""
    from annotate.geometry import rect_iou

    pairs = sorted(((rect_iou(p, t), i, j) for i, (sp, p) in enumerate(props) for j, (st, t) in enumerate(truth)
                    if sp == st), reverse=True)
    used_p, used_t, out = set(), set(), []
    for iou, i, j in pairs:
        if iou < iou_min:
            break
        if i not in used_p and j not in used_t:
            used_p.add(i)
            used_t.add(j)
            out.append(iou)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--project", default=str(REPO / "datasets" / "real-photos"), help="labelled photo project")
    ap.add_argument("--split", default="test", help="photos of this SOURCES.tsv split (default test; all: every one)")
    ap.add_argument("--weights", default=None, help="model (default: the shipped one)")
    ap.add_argument("--split-step", type=float, action="append", default=None, metavar="M",
                    help="racklay.reasoning split_step_m for reading proposals; repeat to compare (default: 0 and "
                         "the default)")
    ap.add_argument("--gap-depth", type=float, action="append", default=None, metavar="D",
                    help="annotate.geometry.GapSplit depth: cut proposals at the photo's gaps this deep; 0: no cut; "
                         "repeat to compare (default: 0 and the default)")
    ap.add_argument("--load-width", type=float, action="append", default=None, metavar="M",
                    help="racklay.reasoning load_width_m for reading proposals (each box run cut into loads of this "
                         "width; 0: not known); repeat to compare (default: 0)")
    ap.add_argument("--iou", type=float, default=0.5, help="a proposal this close to a label stack is accepted")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--flip-average", action="store_true",
                    help="the model predicts with test-time flip averaging (`racklay predict --flip-average`; "
                         "whether the annotator's proposals would gain from it)")
    ap.add_argument("--whole-photo", action="store_true",
                    help="the model reads the whole photo, not the crop around the labeller's rack (as the "
                         "annotator did before it read the outlined rack, `racklay predict --rack-box`)")
    add_precision_args(ap)
    args = ap.parse_args(argv)

    from dataclasses import replace

    from annotate import geometry as G
    from annotate.editor import Tool
    from annotate.store import Project
    from racklay.predict import Predictor
    from racklay.reasoning import ReasoningConfig
    from racklay.release import resolve_weights

    proj = Project(args.project)
    names = labelled_photos(proj, args.split, args.limit)
    weights = resolve_weights(args.weights)
    tool = Tool(proj, Predictor(weights, precision=args.precision, flip_average=args.flip_average))
    tool.read_rack_crop = not args.whole_photo
    steps = args.split_step or [0.0, ReasoningConfig().split_step_m]
    depths = args.gap_depth or [0.0, G.GapSplit().depth]
    loads = args.load_width or [0.0]
    settings = [(s, d, w) for s in steps for d in depths for w in loads]
    rows = {k: {"truth": 0, "props": 0, "ious": [], "left": 0} for k in settings}
    row_tools = {k: {"shelves": 0, "parts": 0, "right": 0} for k in ("w", "W")}
    n_truth = 0
    for name in names:
        ann = proj.load(name)
        scene = G.build_scene(ann, proj.settings)
        truth = label_stacks(scene)
        n_truth += len(truth)
        for s, d, w in settings:
            tool.reasoning = replace(ReasoningConfig(), split_step_m=s, load_width_m=w)
            tool.gap_split = replace(G.GapSplit(), depth=d)
            props = tool_proposals(tool, ann, scene)
            r = rows[s, d, w]
            r["truth"] += len(truth)
            r["props"] += len(props)
            ious = match(props, truth, args.iou)
            r["ious"] += ious
            r["left"] += len(props) > len(ious)
        luma = tool.luma(name)
        for i in sorted({sh for sh, _ in truth}):
            ts = [(sh, t) for sh, t in truth if sh == i]
            u0, u1 = min(t[0] for _, t in ts), max(t[1] for _, t in ts)
            v0, v1 = min(t[2] for _, t in ts), max(t[3] for _, t in ts)
            cuts = np.linspace(u0, u1, len(ts) + 1)
            parts = {"w": list(zip(cuts[:-1], cuts[1:])),
                     "W": [(q.u0, q.u1) for q in G.split_at_dark_gaps(G.Proposal(i, u0, u1, v0, v1, None, 0.0), luma,
                                                                      scene.plane, G.GapSplit())]}
            for k, spans in parts.items():
                rt = row_tools[k]
                rt["shelves"] += 1
                rt["parts"] += len(spans)
                rt["right"] += len(match([(i, (a, b, v0, v1)) for a, b in spans], ts, args.iou))
    print(f"{args.project}, split {args.split}: {len(names)} labelled photos; proposals of {Path(weights).name}, "
          f"accepted at IoU >= {args.iou} with a label stack\n")
    print("| step cut | cut at the photo's gaps | load width | label stacks | proposals | accepted | precision | recall "
          "| mean IoU accepted | input for the boxes, s (no model / with proposals) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (s, d, w), r in rows.items():
        acc = len(r["ious"])
        manual = 2 * CLICK_S * r["truth"]
        assisted = KEY_S * (acc + 2 * r["left"]) + 2 * CLICK_S * (r["truth"] - acc)
        print(f"| {s:g} m | {f'depth {d:g}' if d else 'no'} | {f'{w:g} m' if w else '-'} | {r['truth']} | {r['props']} | {acc} | {100 * acc / max(r['props'], 1):.1f} % "
              f"| {100 * acc / max(r['truth'], 1):.1f} % | {sum(r['ious']) / max(acc, 1):.3f} "
              f"| {manual:.0f} / {assisted:.0f} |")
    print(f"\nno model, one box drawn around each shelf's {n_truth} label stacks, then split:\n")
    print("| row tool | shelves | parts | stacks right | input for the boxes, s (one by one / with the row tool) |")
    print("|---|---|---|---|---|")
    for k, rt in row_tools.items():
        what = "`w`: N equal boxes, N typed" if k == "w" else "`W`: at the photo's gaps"
        row_s = rt["shelves"] * (2 * CLICK_S + KEY_S + (NUMBER_S if k == "w" else 0))
        print(f"| {what} | {rt['shelves']} | {rt['parts']} | {rt['right']} | {2 * CLICK_S * n_truth:.0f} / "
              f"{row_s + 2 * CLICK_S * (n_truth - rt['right']):.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
