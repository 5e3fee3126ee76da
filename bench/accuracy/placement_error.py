"""How far a struct model places each shelf from where the image shows it, on any dataset whose
meta has level spans (photos exported by `annotate export`, renders of `racklay synth`):

    .venv/bin/python -m bench.accuracy.placement_error --data /tmp/real131 --split test \
        [--weights W ...] [--limit N]

For every shelf the labels hold and whose span the meta gives, the absolute error of the model's
left and right shelf end (its structure's placement: centre ± half-width, per view) against the
span, in image widths of the model's input (letterbox padding included). Prints, per model and
view, the median and the 90th percentile of each end's error and the share of shelves with both
ends within 0.05 image widths. What `--placement-weight` trains (docs/training.md); on photos the
twenty-sixth session found v9's ends 0.17–0.20 off, on `complex` renders 0.02. Numbers only.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from racklay.predict import add_precision_args


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="RackLay dataset with level_spans in its meta")
    ap.add_argument("--split", default="test", help="split of --data (default test)")
    ap.add_argument("--weights", nargs="+", default=[None],
                    help="struct checkpoints to compare (default: the shipped model)")
    ap.add_argument("--limit", type=int, default=None, help="the first N samples of the split")
    add_precision_args(ap)
    args = ap.parse_args(argv)

    from tqdm import tqdm

    from racklay.evaluate import split_dataset
    from racklay.predict import Predictor
    from racklay.release import resolve_weights
    from racklay.structure import truth_structure
    from racklay.torchdata import data_loader

    print(f"{args.data} [{args.split}]: shelf ends against the labelled spans, image widths "
          "(median / 90th percentile; both ends within 0.05)")
    print("| model | view | shelves | left end | right end | both within 0.05 |\n|---|---|---|---|---|---|")
    for w in args.weights:
        pred = Predictor(str(resolve_weights(w)), precision=args.precision)
        if pred.model is None or pred.cfg.decoder != "struct":
            ap.error(f"{pred.weights}: needs a struct model (its structures carry the placement)")
        _, views, ds = split_dataset(pred, args.data, args.split, args.limit, spans=True)
        name = pred.weights.name if pred.weights.name not in ("last.safetensors", "best.safetensors") \
            else f"{pred.weights.parent.name}/{pred.weights.name}"          # a run's checkpoint: name the run
        errs = {v: [] for v in views}
        loader = data_loader(ds, 0, batch_size=8, shuffle=False)
        for batch in tqdm(loader, desc=name, unit="batch", file=sys.stderr):
            structs = pred.structures(batch["image"])
            spans = batch["spans"].numpy()                                         # (N, R, 2)
            for v in views:
                st = structs[v]
                present = truth_structure(v, batch[v].long(), pred.grid.extent, 8)["presence"].numpy()
                c, h = st["centre"].float().numpy(), st["half"].float().numpy()
                ends = np.stack([0.5 + c - h, 0.5 + c + h], -1)
                ok = present & np.isfinite(spans).all(-1)
                errs[v].append(np.abs(ends - spans)[ok])
        for v in views:
            e = np.concatenate(errs[v]) if errs[v] else np.zeros((0, 2))
            if not len(e):
                print(f"| {name} | {v} | 0 | - | - | - |")
                continue
            med, p90 = np.median(e, 0), np.percentile(e, 90, 0)
            print(f"| {name} | {v} | {len(e)} | {med[0]:.3f} / {p90[0]:.3f} | {med[1]:.3f} / {p90[1]:.3f} "
                  f"| {100 * (e.max(1) <= 0.05).mean():.0f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
