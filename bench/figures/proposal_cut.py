"""Regenerate docs/img/annotate-proposals.jpg: the annotator's model proposals on labelled photos
before and after the cut at the photo's gaps, side by side, with the labelled box stacks.

    .venv/bin/python -m bench.figures.proposal_cut [--photo NAME ...] [--weights FILE] [--out FILE]

For each photo the labeller's own rack and shelves are given to the tool with no boxes, as
`bench/accuracy/proposal_quality.py` does, and the tool proposes boxes twice: as it did before
(racklay.reasoning's 8 cm step cut, no photo gaps) and as it does now (`annotate.editor.Tool`'s
defaults). Green: proposals; thin red: the labels' box stacks; the count of proposals a
labeller would accept (IoU >= 0.5 with a stack) in each panel's corner.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from bench.common import REPO
from racklay.predict import add_precision_args

#: test-site photos (never trained on) and a training-site shelving photo
PHOTOS = ("24_palletvid0261_f044.jpg", "117_palletvid0265_f217.jpg", "06_blueshelf_mixed.jpg")
PANEL_W = 560


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photo", action="append", default=None, help=f"labelled photo (default: {', '.join(PHOTOS)})")
    ap.add_argument("--project", default=str(REPO / "datasets" / "real-photos"), help="labelled photo project")
    ap.add_argument("--weights", default=None, help="model (default: the shipped one)")
    ap.add_argument("--out", default=str(REPO / "docs" / "img" / "annotate-proposals.jpg"))
    add_precision_args(ap)
    args = ap.parse_args(argv)

    import cv2
    import numpy as np

    from annotate import geometry as G
    from annotate import schema as S
    from annotate.editor import Tool
    from annotate.store import Project
    from bench.accuracy.proposal_quality import label_stacks, match, tool_proposals
    from racklay.atomic import atomic_write_bytes
    from racklay.predict import Predictor
    from racklay.reasoning import ReasoningConfig
    from racklay.release import resolve_weights

    proj = Project(args.project, create=False)
    tool = Tool(proj, Predictor(str(resolve_weights(args.weights)), precision=args.precision))
    now_reasoning, now_cut = tool.reasoning, tool.gap_split
    settings = {"before: step cut": (ReasoningConfig(), replace(now_cut, depth=0.0)),
                "now: cut at the photo's gaps": (now_reasoning, now_cut)}
    rows = []
    for name in args.photo or PHOTOS:
        ann = proj.load(name)
        scene = G.build_scene(ann, proj.settings)
        truth = label_stacks(scene)
        photo = G.restore_aspect(proj.read_image(name), S.pixel_aspect(proj.settings))
        scale = PANEL_W / photo.shape[1]
        panels = []
        for title, (reasoning, cut) in settings.items():
            tool.reasoning, tool.gap_split = reasoning, cut
            props = tool_proposals(tool, ann, scene)
            img = cv2.resize(photo, (PANEL_W, round(photo.shape[0] * scale)), interpolation=cv2.INTER_AREA)
            for rects, colour, width, inset in ((truth, (230, 40, 40), 1, 0.0), (props, (40, 230, 40), 2, 0.015)):
                for _, (u0, u1, v0, v1) in rects:
                    q = G.rect_outline(scene.plane, u0 + inset, u1 - inset, v0 + inset, v1 - inset) * scale
                    cv2.polylines(img, [np.round(q).astype(np.int32)], True, colour, width, cv2.LINE_AA)
            text = f"{title}: {len(match(props, truth, 0.5))} of {len(truth)} stacks as proposed"
            bar = np.full((26, PANEL_W, 3), 255, np.uint8)
            cv2.putText(bar, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
            panels.append(np.vstack([bar, img]))
        rows.append(np.hstack([panels[0], np.full((panels[0].shape[0], 8, 3), 255, np.uint8), panels[1]]))
    width = max(r.shape[1] for r in rows)
    sheet = np.vstack([np.pad(r, ((0, 8), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows])
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 80])
    if not ok:
        raise SystemExit(f"{args.out}: could not encode the figure")
    atomic_write_bytes(args.out, buf.tobytes())
    print(f"figure: {args.out} ({len(buf) // 1024} KB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
