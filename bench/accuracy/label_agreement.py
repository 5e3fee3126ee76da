"""How far apart are two labellings of the same photos? The noise floor of every real-photo score.

    .venv/bin/python -m bench.accuracy.label_agreement [--a datasets/real-photos] [--b datasets/real-photos/agreement]

`--a` is an `annotate` project (photos + annotations/); `--b` a folder whose `annotations/`
holds a second, independent labelling of some of the same photos (same file names). Both
labellings are turned into layouts by the tool's own geometry (annotate.dataset.annotation_layouts,
the grid of project A) and compared cell by cell, with A as the reference (IoU is symmetric):

* metric: each labelling with its own rack size, as exported;
* shared size: B re-mapped with A's rack width, height and depth (same clicks), i.e. the
  disagreement of the clicks alone, without the size estimate.

Prints per photo and pooled (dataset-level) shelf and box IoU per view. Asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bench.common import REPO


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--a", type=Path, default=REPO / "datasets" / "real-photos", help="annotate project (reference)")
    ap.add_argument("--b", type=Path, default=REPO / "datasets" / "real-photos" / "agreement",
                    help="folder with annotations/ of a second labelling of photos of --a")
    args = ap.parse_args()

    from annotate.dataset import annotation_layouts
    from annotate.store import Project
    from racklay.metrics import confusion, confusion_scores

    project = Project(args.a, create=False)
    files = sorted((args.b / "annotations").glob("*.json"))
    if not files:
        raise SystemExit(f"{args.b / 'annotations'}: no annotation files")
    views = ("top", "front")
    pooled = {k: {v: 0 for v in views} for k in ("metric", "shared size")}
    rows = []
    for f in files:
        try:
            b = json.loads(f.read_text())
        except ValueError as e:
            raise SystemExit(f"{f}: not valid JSON ({e})") from None
        name = b.get("image")
        if name not in project.images():
            raise SystemExit(f"{f}: photo {name!r} is not in {args.a}")
        a = project.read_annotation(name)
        if a is None:
            raise SystemExit(f"{f}: {name} has no annotation in {args.a}")
        shared = json.loads(json.dumps(b))
        shared["rack"].update({k: a["rack"][k] for k in ("width", "height", "depth")})
        ref = annotation_layouts(project, a)[:2]
        row = [name, f"{a['rack']['width']:.2f}/{b['rack']['width']:.2f}"]
        for kind, ann in (("metric", b), ("shared size", shared)):
            got = annotation_layouts(project, ann)[:2]
            for v, r, g in zip(views, ref, got):
                cm = confusion(g, r)
                pooled[kind][v] = pooled[kind][v] + cm
                s = confusion_scores(cm)
                row.append(f"{100 * s['box']['IoU']:.0f}")
        rows.append(row)
    print(f"{len(rows)} photos labelled twice ({args.a} vs {args.b}); box IoU per photo, top / front")
    print("| photo | rack width A/B (m) | metric top | metric front | shared size top | shared size front |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    print("\npooled over all photos (dataset-level IoU, %):")
    print("| | top shelf | top box | front shelf | front box |")
    print("|---|---|---|---|---|")
    for kind, cms in pooled.items():
        cells = []
        for v in views:
            s = confusion_scores(cms[v])
            cells += [f"{100 * s['shelf']['IoU']:.1f}", f"{100 * s['box']['IoU']:.1f}"]
        print(f"| {kind} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
