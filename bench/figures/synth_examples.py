"""Regenerate docs/img/waresynth_examples.png: a few images of each WareSynth recipe with their
per-shelf top/front layouts, drawn with `racklay show`; with --sheet RECIPE, a contact sheet of
16 renders of one recipe instead (docs/img/waresynth_<recipe>.jpg), to look at a style as a whole.

    .venv/bin/python -m bench.figures.synth_examples [--per-recipe 2] [--out docs/img/waresynth_examples.png]
    .venv/bin/python -m bench.figures.synth_examples --sheet pallet
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from bench.common import REPO


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--per-recipe", type=int, default=2)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--out", default=None, help="output image (default docs/img/waresynth_examples.png, "
                    "with --sheet docs/img/waresynth_<recipe>.jpg)")
    ap.add_argument("--sheet", default=None, metavar="RECIPE", help="a 4 x 4 contact sheet of this recipe instead")
    args = ap.parse_args(argv)
    img_dir = REPO / "docs" / "img"
    if args.sheet:
        return contact_sheet(args.sheet, args.seed, args.out or str(img_dir / f"waresynth_{args.sheet}.jpg"))
    args.out = args.out or str(img_dir / "waresynth_examples.png")

    import cv2
    import numpy as np

    from racklay.atomic import atomic_save_png
    from racklay.cli import main as racklay_main
    from racklay.data import read_image

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for recipe in ("simple", "complex", "proxy_real"):
            ds = Path(tmp) / recipe
            n = 4 * args.per_recipe
            assert racklay_main(["synth", "--recipe", recipe, "--n", str(n), "--out", str(ds),
                                 "--seed", str(args.seed), "--no-progress"]) == 0
            # show variety: prefer samples whose (background, visible shelves) differ
            from racklay.data import RackLayRoot
            root, picked, keys = RackLayRoot(ds), [], set()
            for i in range(n):
                m = root.read_meta(f"{i:06d}")
                key = (m["background"], len(m["rack"]["visible_shelves"]))
                if key[0] not in {k[0] for k in keys} or (len(keys) and key not in keys and len(picked) > 1):
                    picked.append(i)
                    keys.add(key)
            picked = (picked + [i for i in range(n) if i not in picked])[:args.per_recipe]
            figs = []
            for i in picked:
                fig = Path(tmp) / f"{recipe}_{i}.png"
                assert racklay_main(["show", str(ds), "--index", str(i), "--out", str(fig)]) == 0
                figs.append(read_image(fig))
            h = min(f.shape[0] for f in figs)
            rows.append(np.concatenate([cv2.resize(f, (int(f.shape[1] * h / f.shape[0]), h)) for f in figs], axis=1))
    w = min(r.shape[1] for r in rows)
    grid = np.concatenate([cv2.resize(r, (w, int(r.shape[0] * w / r.shape[1]))) for r in rows], axis=0)
    scale = min(1.0, 2400 / grid.shape[1])
    grid = cv2.resize(grid, (int(grid.shape[1] * scale), int(grid.shape[0] * scale)), interpolation=cv2.INTER_AREA)
    atomic_save_png(args.out, grid)
    print(f"wrote {args.out} ({grid.shape[1]}x{grid.shape[0]})")
    return 0


def contact_sheet(recipe: str, seed: int, out: str) -> int:
    import cv2
    import numpy as np

    from racklay.atomic import atomic_write_bytes
    from racklay.cli import main as racklay_main
    from racklay.data import read_image

    with tempfile.TemporaryDirectory() as tmp:
        ds = Path(tmp) / recipe
        assert racklay_main(["synth", "--recipe", recipe, "--n", "16", "--out", str(ds), "--seed", str(seed),
                             "--no-progress"]) == 0
        ims = [read_image(p) for p in sorted((ds / "Images").iterdir())]
    rows = [np.concatenate(ims[i:i + 4], axis=1) for i in range(0, 16, 4)]
    grid = np.concatenate(rows, axis=0)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(grid, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 82])
    atomic_write_bytes(out, buf.tobytes())
    print(f"wrote {out} ({grid.shape[1]}x{grid.shape[0]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
