"""Seconds per training image of RackLay-D (both views): the default `light` decoder vs the
authors' `paper` decoder, in the same run.

    MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296 \
        nice -n 5 .venv/bin/python -m bench.speed.train_speed [--size 256] [--batch 8] [--disc] [--bf16]

(the script re-executes itself with those MALLOC_* variables if they are missing: glibc reads
them at process start). One step is the training loop's own, `racklay.train.train_step` (forward,
the default losses of TrainConfig over both views, backward, Adam), on a run set up by
`racklay.train.build_run` as `racklay train` sets it up (channels_last on CPU). With --disc the
least-squares adversarial terms (generator + discriminator update) are included. Data come from
random tensors, so the
number is the model's cost alone (data loading is excluded). Steps of the two models are
interleaved in rounds; the step time divided by the batch size is reported (wall median and
minimum, and the process CPU time, which is least disturbed by other jobs with --threads 1). Prints
numbers only; nothing is asserted.
"""
from __future__ import annotations

import argparse
import json
import sys

from bench.common import add_common_args, conditions, ensure_malloc_env, interleaved, markdown_table, start, summarise


def make_step(decoder: str, size: int, batch: int, disc: bool, bf16: bool):
    """A closure running one step of `racklay.train.train_step` on a run built as `racklay train`
    builds it (`build_run`: models, optimisers, precision, memory format), ResNet-18 encoder,
    random weights, default losses and class weights, on one fixed random batch."""
    import tempfile
    import time
    from pathlib import Path

    import torch

    from racklay.config import TrainConfig
    from racklay.distributed import Dist
    from racklay.train import build_run, models_for_epoch, train_step

    cfg = TrainConfig(image_size=size, layout_size=size, decoder=decoder, disc=disc, encoder="resnet18",
                      pretrained=False, amp="bf16" if bf16 else "fp32", device="cpu", progress=False)
    run = build_run(cfg, Dist(cfg.device), Path(tempfile.gettempdir()), time.time(), init=False)
    gen, discs = models_for_epoch(run, cfg.disc_start if disc else 0)   # discriminators on, if any
    g = torch.Generator().manual_seed(1)
    data = {"image": torch.randn(batch, 3, size, size, generator=g),
            **{v: torch.randint(0, 3, (batch, cfg.R, size, size), generator=g) for v in cfg.views}}
    return lambda: train_step(run, gen, discs, data)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, nargs="+", default=[256], help="square input = layout size(s) (default 256)")
    ap.add_argument("--batch", type=int, default=8, help="images per step (default 8)")
    ap.add_argument("--disc", action="store_true", help="include the patch discriminators (-disc variant)")
    ap.add_argument("--bf16", action="store_true", help="bf16 autocast instead of fp32")
    add_common_args(ap, rounds=3, calls=2, warmup=1)
    args = ap.parse_args(argv)
    start(args)
    print("step: racklay.train.train_step (the training loop's own step) on a run built by racklay.train.build_run")
    mode = ("bf16" if args.bf16 else "fp32") + " + channels_last" + (", with discriminators" if args.disc else "")
    rows, results = [], {}
    for size in args.size:
        steps = {d: make_step(d, size, args.batch, args.disc, args.bf16) for d in ("light", "paper")}
        times = interleaved(steps, args)
        st = {d: summarise(t, 1.0 / args.batch) for d, t in times.items()}
        results[size] = st
        for d in ("light", "paper"):
            rows.append([f"{size}->{size}", d, f"{st[d]['wall_median']:.3f} ({st[d]['wall_min']:.3f})",
                         f"{st[d]['cpu_median']:.3f}", f"{st[d]['wall_median'] * 2000 / 60:.1f}"])
        p, lt = st["paper"], st["light"]
        rows.append([f"{size}->{size}", "**paper / light**",
                     f"**{p['wall_median'] / lt['wall_median']:.1f}x** (min {p['wall_min'] / lt['wall_min']:.1f}x)",
                     f"{p['cpu_median'] / lt['cpu_median']:.1f}x", ""])
        print(f"  {size}: light {lt['wall_median']:.3f} s/img, paper {p['wall_median']:.3f} s/img (wall medians)", flush=True)
    print()
    print(f"RackLay-D training, batch {args.batch}, {mode}, {args.rounds}x{args.calls} interleaved steps per model:")
    print(markdown_table(["input->layout", "decoder", "s / training image: wall median (min)", "CPU s / image",
                          "min / 2,000-image epoch (wall median)"], rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"conditions": conditions(), "mode": mode, "batch": args.batch, "results": results}, f, indent=1)
    return 0


if __name__ == "__main__":
    ensure_malloc_env()
    sys.exit(main())
