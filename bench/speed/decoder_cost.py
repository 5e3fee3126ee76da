"""What the struct decoder's latency is made of: would a narrower decoder (a retrain) bring the
reference architecture to >= 3x slower than the shipped model (the model issue's speed target)?

    nice -n 5 .venv/bin/python -m bench.speed.decoder_cost [--precision auto|fp32|bf16] [--batch N]

Builds the shipped architecture (EfficientNet-Lite0 + `struct`) with the struct decoder at several
widths (`StructDecoder(width=...)`: every 1-D conv and the fuse conv) with and without the
1/4 detail branch, with the fuse conv 3 x 3 or 1 x 1 (`--struct-fuse-k`) and with one trunk for both
views (`--struct-joint`), randomly initialised
(weights do not change the cost), and times each against
the reference (ResNet-18 + `paper`) at the shipped input, layout size and precision, channels_last,
calls interleaved in rounds. Prints per model: wall ms median (min), the decoders' multiply-adds
(torch's FLOP counter, both views) and reference / model. If the ratio barely moves while the
decoders' multiply-adds fall several-fold, the decoder's cost at this batch is per-layer overhead,
not arithmetic, and no narrower decoder of this design meets the target. Prints numbers only.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from bench.common import (
    add_batch_arg,
    add_common_args,
    ensure_malloc_env,
    forward_runner,
    interleaved,
    markdown_table,
    reference_model,
    start,
    summarise,
)
from racklay.predict import add_precision_args

WIDTHS = (128, 64, 32)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_precision_args(ap)
    add_batch_arg(ap)
    add_common_args(ap, rounds=3, calls=5, warmup=2)
    args = ap.parse_args(argv)
    start(args)
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from racklay.checkpoint import load_model
    from racklay.model import RackLayNet
    from racklay.precision import resolve_precision
    from racklay.release import resolve_weights

    prec = resolve_precision(args.precision)
    _, cfg, _ = load_model(resolve_weights(None))
    torch.manual_seed(0)
    models = {}
    for fine, fuse_k, joint in ((True, 3, False), (False, 3, False), (False, 1, False), (False, 1, True)):
        for width in WIDTHS:
            m = RackLayNet(replace(cfg, decoder="struct", struct_fine=fine, struct_width=width, struct_fuse_k=fuse_k,
                                   struct_joint=joint))
            shipped = (width, fine, fuse_k, joint) == (cfg.struct_width, cfg.struct_fine, cfg.struct_fuse_k,
                                                       cfg.struct_joint)
            name = (f"struct width {width}{', 1/4 branch' if fine else ''}{', 1x1 fuse' if fuse_k == 1 else ''}"
                    f"{', one trunk' if joint else ''}")
            models[name + (" (shipped)" if shipped else "")] = m.eval()
    models["reference (ResNet-18 + paper)"] = reference_model(cfg)
    h, w = cfg.input_hw
    x = torch.randn(args.batch, 3, h, w)
    macs = {}
    for k, m in models.items():
        fc = FlopCounterMode(display=False)
        with torch.no_grad(), fc:
            m(x[:1])
        enc = FlopCounterMode(display=False)
        with torch.no_grad(), enc:
            m.encoder(x[:1])
        macs[k] = (fc.get_total_flops() - enc.get_total_flops()) / 2e6
    x = x.contiguous(memory_format=torch.channels_last)
    models = {k: m.to(memory_format=torch.channels_last) for k, m in models.items()}
    bf16 = prec == "bf16"
    first = next(iter(models.values()))
    runners = {k: forward_runner(m, x, bf16) for k, m in models.items()}
    runners["encoder alone (a decoder costing nothing)"] = forward_runner(first.encoder, x, bf16)
    times = interleaved(runners, args)
    st = {k: summarise(v, 1000.0) for k, v in times.items()}
    ref = st["reference (ResNet-18 + paper)"]["wall_median"]
    rows = [[k, f"{s['wall_median']:.1f} ({s['wall_min']:.1f})", f"{macs[k]:.0f}" if k in macs else "0",
             f"{ref / s['wall_median']:.2f}x"] for k, s in st.items()]
    print(f"\nbatch {args.batch} (times per call), both views, input {w}x{h} -> layouts {cfg.layout_size}, {prec}, "
          f"channels_last, {args.rounds}x{args.calls} interleaved calls per model (target: reference >= 3x slower):")
    print(markdown_table(["model", "wall ms median (min)", "decoders' M multiply-adds per image",
                          "reference / model"], rows))
    return 0


if __name__ == "__main__":
    ensure_malloc_env()
    sys.exit(main())
