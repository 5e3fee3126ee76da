"""Seconds per training image of RackLay-D (both views): the default `light` decoder vs the
authors' `paper` decoder, in the same run.

    MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296 \
        nice -n 5 .venv/bin/python bench/train_speed.py [--size 256] [--batch 8] [--disc] [--bf16]

(the script re-executes itself with those MALLOC_* variables if they are missing: glibc reads
them at process start). One step = forward, per-shelf weighted cross-entropy ([1, 5, 5]) over
both views (`racklay.losses.layout_loss`), backward and an Adam update, in the same sequence as
the loop in `racklay.train.train` (which has no separate step function to call). With
--disc the least-squares adversarial terms (generator + discriminator update, patch
discriminators fed softmax probabilities) are included. Data come from random tensors, so the
number is the model's cost alone (data loading is excluded). Steps of the two models are
interleaved in rounds; the step time divided by the batch size is reported (wall median and
minimum, and the process CPU time, which is least disturbed by other jobs with --threads 1). Prints
numbers only; nothing is asserted.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import add_common_args, conditions, ensure_malloc_env, interleaved, markdown_table, start, summarise  # noqa: E402

CLASS_WEIGHTS = (1.0, 5.0, 5.0)


def make_step(decoder: str, size: int, batch: int, disc: bool, bf16: bool, lr: float = 1e-4):
    import torch

    from racklay.losses import layout_loss, lsgan_discriminator_loss, lsgan_generator_loss, one_hot_layouts
    from racklay.model import Discriminators, ModelConfig, RackLayNet

    torch.manual_seed(0)
    cfg = ModelConfig(image_size=size, layout_size=size, views=("top", "front"), decoder=decoder, disc=disc,
                      encoder="resnet18")
    model = RackLayNet(cfg).train()
    discs = Discriminators(cfg).train() if disc else None
    if bf16:
        model = model.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    opt_d = torch.optim.Adam(discs.parameters(), lr=lr, betas=(0.5, 0.999)) if disc else None
    x = torch.randn(batch, 3, size, size)
    if bf16:
        x = x.contiguous(memory_format=torch.channels_last)
    g = torch.Generator().manual_seed(1)
    y = {v: torch.randint(0, 3, (batch, cfg.R, size, size), generator=g) for v in cfg.views}
    w = torch.tensor(CLASS_WEIGHTS)
    lam = 0.01

    def step():  # the same sequence as the loop in racklay.train.train()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = model(x)
        loss = sum(layout_loss(out[v], y[v], w) for v in cfg.views)
        probs = {}
        if disc:
            discs.requires_grad_(False)
            adv = 0.0
            for v in cfg.views:
                probs[v] = out[v].float().softmax(2)
                with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                    adv = adv + lsgan_generator_loss(discs(v, probs[v]).float())
            discs.requires_grad_(True)
            loss = loss + lam * adv
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if disc:
            ld = 0.0
            for v in cfg.views:
                both = torch.cat([one_hot_layouts(y[v]), probs[v].detach()])
                with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                    scores = discs(v, both).float()
                ld = ld + lsgan_discriminator_loss(scores[:batch], scores[batch:])
            opt_d.zero_grad(set_to_none=True)
            ld.backward()
            opt_d.step()

    return step


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, nargs="+", default=[256], help="square input = layout size(s) (default 256)")
    ap.add_argument("--batch", type=int, default=8, help="images per step (default 8)")
    ap.add_argument("--disc", action="store_true", help="include the patch discriminators (-disc variant)")
    ap.add_argument("--bf16", action="store_true", help="bf16 autocast + channels_last instead of fp32")
    add_common_args(ap, rounds=3, calls=2, warmup=1)
    args = ap.parse_args(argv)
    start(args)
    print("step: the sequence of racklay.train's loop (its layout_loss, weighted CE [1,5,5]) + backward + Adam")
    mode = ("bf16+CL" if args.bf16 else "fp32") + (", with discriminators" if args.disc else "")
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
