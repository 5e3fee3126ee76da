"""Fine-tuning the shipped model on proxy-real: its own loss weighting vs the default 1 / 5 / 5.

  .venv/bin/python -m bench.accuracy.finetune_class_weights [--weights FILE] [--real DIR] [--epochs 8]

`transfer finetune` keeps the class weights the checkpoint was trained with (the release model's
are 1 / 5 / 10: background / shelf / box). This bench measures why: it fine-tunes the same model
on the demo's proxy-real set (`transfer demo`'s 200 images, rendered as
it renders them: seed 1, 163 train / 37 test) twice, for a fixed number of epochs (not a time budget, so a busy
machine gives the same runs), once with the checkpoint's weights and once with 1 / 5 / 5, and
scores both, and the model before fine-tuning, on the test split. Prints a table; asserts nothing.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--weights", default=None, help="model to fine-tune (default: the shipped one)")
    ap.add_argument("--real", default="/work/data/demo_proxy_real", type=Path,
                    help="proxy-real root with train/test splits (rendered as the demo does if missing)")
    ap.add_argument("--epochs", type=int, default=8, help="fine-tuning epochs per arm (default 8)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="run folders (default: a temporary folder, removed)")
    args = ap.parse_args()

    from racklay.evaluate import evaluate
    from racklay.release import resolve_weights
    from transfer import workflow

    if not (args.real / "splits" / "test.txt").is_file():
        from racklay.synth.generate import generate_dataset
        from racklay.synth.recipe import load_recipe
        from transfer.demo import DemoConfig

        d = DemoConfig()   # the demo's set: its size, seed and layout size
        print(f"rendering the demo's proxy-real set into {args.real}", flush=True)
        generate_dataset(load_recipe("proxy_real", {"layout_size": d.layout_d}), d.n_real, args.real, seed=d.real_seed,
                         workers=2)
    weights = resolve_weights(args.weights)
    own = workflow.checkpoint_loss(weights).get("class_weights")
    print(f"model {weights}: trained with class weights {own}", flush=True)
    tmp = tempfile.TemporaryDirectory(prefix="racklay-ftcw-")
    out = Path(args.out or tmp.name)

    def score(w) -> dict:
        res = evaluate(str(w), args.real, split="test", progress=False)
        return {f"{v} {c}": 100 * res[v]["dataset"][k]["IoU"] for v in ("top", "front")
                for c, k in (("shelf", "shelf"), ("box", "box"))} | {
            "top box mIoU": 100 * res["top"]["paper"]["box"]["mIoU"]}

    rows = [("before fine-tuning", 0.0, score(weights))]
    for label, cw in ((f"checkpoint's {','.join(f'{v:g}' for v in own)}" if own else "TrainConfig's", None),
                      ("1,5,5", (1.0, 5.0, 5.0))):
        t0 = time.time()
        run = workflow.finetune(weights, args.real, out, name=f"ft-{label.split()[-1].replace(',', '-')}",
                                seed=args.seed, epochs=args.epochs, batch_size=8, class_weights=cw,
                                max_minutes=None, patience=args.epochs + 1, progress=False, workers=0)
        rows.append((f"fine-tuned, class weights {label}", time.time() - t0,
                     score(workflow.best_weights(run))))
    cols = list(rows[0][2])
    print(f"\nproxy-real test split ({args.real}), {args.epochs} fine-tuning epochs per arm, dataset-level IoU x100")
    print("| model | " + " | ".join(cols) + " | train s |")
    print("|---|" + "---|" * (len(cols) + 1))
    for label, secs, m in rows:
        print(f"| {label} | " + " | ".join(f"{m[c]:.2f}" for c in cols) + f" | {secs:.0f} |")
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
