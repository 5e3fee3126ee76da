"""Batch-1 inference latency of RackLay-D (both views): the default `light` decoder vs the
authors' `paper` decoder, in the same run, at 256->256 and 512->512 (input -> layout size).

    MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296 \
        nice -n 5 .venv/bin/python -m bench.speed.inference_speed [--sizes 256 512] [--bf16] [--onnx]

(the script re-executes itself with those MALLOC_* variables if they are missing: glibc reads
them at process start). Models are randomly initialised (weights do not change the cost).
Timing interleaves the models in rounds so that load from other processes hits all of them alike;
each cell gives the median (and minimum) wall time over all timed calls and the median process
CPU time (ms): on a machine shared with other jobs, the minimum and the CPU time (best with
--threads 1) are the least disturbed estimates of the model's own cost. Columns: torch fp32; with --bf16,
torch autocast bfloat16 + channels_last (plus an "as shipped" row: the paper decoder in fp32, as the
authors ran it, against the default model in bf16, what `--precision auto` runs on a CPU with
native bf16); with --onnx, onnxruntime fp32 (CPU provider). Prints
numbers only; nothing is asserted.
"""
from __future__ import annotations

import argparse
import json
import sys

from bench.common import add_common_args, conditions, ensure_malloc_env, interleaved, markdown_table, start, summarise


def build_runners(decoder: str, size: int, bf16: bool, onnx: bool, threads: int | None = None) -> dict:
    import numpy as np
    import torch

    from racklay.model import ModelConfig, RackLayNet

    torch.manual_seed(0)
    encoder_only = decoder == "encoder"
    cfg = ModelConfig(image_size=size, layout_size=size, views=("top", "front"), encoder="resnet18",
                      decoder="light" if encoder_only else decoder)
    model = RackLayNet(cfg).eval()
    x = torch.randn(1, 3, size, size)
    runners = {}
    part = (lambda m: m.encoder) if encoder_only else (lambda m: m)

    def fp32():
        with torch.inference_mode():
            part(model)(x)

    runners["torch fp32"] = fp32
    if bf16:
        model_cl = RackLayNet(cfg).eval().to(memory_format=torch.channels_last)
        model_cl.load_state_dict(model.state_dict())
        x_cl = x.contiguous(memory_format=torch.channels_last)

        def bf():
            with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
                part(model_cl)(x_cl)

        runners["torch bf16+CL"] = bf
    if onnx and not encoder_only:
        import onnxruntime as ort

        from racklay.onnx import export_onnx_bytes

        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        if threads:
            opts.intra_op_num_threads = threads
        sess = ort.InferenceSession(export_onnx_bytes(model, cfg), sess_options=opts,
                                    providers=["CPUExecutionProvider"])
        xn = x.numpy().astype(np.float32)
        runners["onnxruntime fp32"] = lambda: sess.run(None, {"image": xn})
    return runners


def cell(s: dict) -> str:
    return f"{s['wall_median']:.0f} ({s['wall_min']:.0f}), cpu {s['cpu_median']:.0f}"


def ratio(a: dict, b: dict) -> str:
    return f"**{a['wall_median'] / b['wall_median']:.1f}x** (min {a['wall_min'] / b['wall_min']:.1f}x, cpu {a['cpu_median'] / b['cpu_median']:.1f}x)"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512], help="square input = layout sizes")
    ap.add_argument("--bf16", action="store_true", help="add a bf16 autocast + channels_last column")
    ap.add_argument("--onnx", action="store_true", help="add an onnxruntime column")
    ap.add_argument("--encoder", action="store_true",
                    help="add a row timing the shared ResNet-18 encoder alone (the floor of any decoder)")
    add_common_args(ap, rounds=3, calls=5, warmup=2)
    args = ap.parse_args(argv)
    start(args)
    results = {}
    rows = []
    for size in args.sizes:
        decs = ("light", "paper") + (("encoder",) if args.encoder else ())
        runners = {dec: build_runners(dec, size, args.bf16, args.onnx, args.threads) for dec in decs}
        times = interleaved({(d, k): fn for d, rs in runners.items() for k, fn in rs.items()}, args)
        cols = list(runners["light"])
        st = {key: summarise(v, 1000.0) for key, v in times.items()}
        results[size] = {f"{d} {k}": st[(d, k)] for (d, k) in times}
        for d in decs:
            rows.append([f"{size}->{size}", "ResNet-18 encoder only" if d == "encoder" else d] +
                        [cell(st[(d, k)]) if (d, k) in st else "n/a" for k in cols])
        rows.append([f"{size}->{size}", "**paper / light**"] + [ratio(st[("paper", k)], st[("light", k)]) for k in cols])
        if ("light", "torch bf16+CL") in st:   # `racklay predict --precision auto` on a native-bf16 CPU
            shipped = ratio(st[("paper", "torch fp32")], st[("light", "torch bf16+CL")])
            rows.append([f"{size}->{size}", "**as shipped: paper fp32 / light bf16+CL**", shipped] +
                        [""] * (len(cols) - 1))
        print(f"  {size}: " + ", ".join(f"{d} {k} {cell(st[(d, k)])}" for (d, k) in times), flush=True)
    header = ["input->layout", "decoder"] + [f"{k}: wall median (min), CPU ms" for k in cols]
    print()
    print(f"RackLay-D (both views), batch 1, {args.rounds}x{args.calls} interleaved calls per cell:")
    print(markdown_table(header, rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"conditions": conditions(), "results": results}, f, indent=1)
    return 0


if __name__ == "__main__":
    ensure_malloc_env()
    sys.exit(main())
