"""Inference latency (batch 1 unless `--batch N`) of the shipped model against the reference architecture (ResNet-18 +
the authors' `paper` decoder) at the shipped input and layout size and the same precision
(the model issue's target: the reference >= 3x slower than the shipped struct model).

    nice -n 5 .venv/bin/python -m bench.speed.release_speed [--weights FILE] [--precision auto|fp32|bf16] [--onnx] [--batch N]
        [--flip-average]

Both models run both views, in the memory format given (default channels_last, as `racklay
predict` runs a model; `--memory-format contiguous` gives the default PyTorch layout) and with
their batch norms folded into the convolutions, as `racklay predict` runs a model
(`racklay.model.fold_batchnorm`; a row gives the shipped model as trained, what folding buys;
`--unfolded` runs both as trained); the
reference is randomly initialised (weights do not change the cost). With a `fast`-decoder model
the same weights also run as `light` (what the decoder arrangement buys). The shipped model's
encoder also runs alone: reference / encoder is the ceiling of the ratio for any decoder on that
encoder. Calls are interleaved in rounds so that load from other processes hits all alike; the
table gives median (min) wall ms and median process CPU ms. Prints numbers only.
"""
from __future__ import annotations

import argparse
import copy
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=None, help="model (default: the shipped one)")
    add_precision_args(ap)
    ap.add_argument("--memory-format", choices=("channels_last", "contiguous"), default="channels_last",
                    help="both models in this layout (default channels_last: what racklay predict uses)")
    ap.add_argument("--onnx", action="store_true",
                    help="also run both models through onnxruntime (fp32, graphs as `racklay export` writes them), "
                         "in the same interleaved rounds")
    ap.add_argument("--flip-average", action="store_true",
                    help="also time the shipped model with test-time flip averaging (`racklay predict "
                         "--flip-average`: the photo and its mirror image in one batch): what its accuracy costs")
    ap.add_argument("--unfolded", action="store_true",
                    help="run both models with their batch norms as trained (default: folded into the convolutions, "
                         "as racklay predict runs a model)")
    add_batch_arg(ap, ": one photo at a time, as the target is stated; larger batches spread the per-layer "
                      "overhead that dominates the struct decoder at batch 1")
    add_common_args(ap, rounds=3, calls=5, warmup=2)
    args = ap.parse_args(argv)
    start(args)
    import torch

    from racklay.checkpoint import load_model
    from racklay.model import RackLayNet, fold_batchnorm
    from racklay.precision import resolve_precision
    from racklay.release import resolve_weights

    prec = resolve_precision(args.precision)
    shipped, cfg, _ = load_model(resolve_weights(args.weights))
    reference = reference_model(cfg)
    h, w = cfg.input_hw
    x = torch.randn(args.batch, 3, h, w)
    bf16 = prec == "bf16"
    models = {f"shipped (EfficientNet-Lite0 + {cfg.decoder})": shipped.eval(), "reference (ResNet-18 + paper)": reference}
    if cfg.decoder == "fast":   # the same tensors in light's order (v5's decoder): what the decoder change bought
        as_light = RackLayNet(replace(cfg, decoder="light")).eval()
        as_light.load_state_dict(shipped.state_dict())
        models["shipped weights, light decoder"] = as_light
    if args.flip_average:
        flipped = load_model(resolve_weights(args.weights))[0].eval()
        flipped.set_flip_average(True)
        models["shipped, flip-averaged"] = flipped
    if not args.unfolded:   # (onnxruntime folds the norms of a graph itself either way)
        as_trained = copy.deepcopy(shipped)
        for m in models.values():
            fold_batchnorm(m)
        models["shipped, batch norms as trained"] = as_trained
    ort_runners = {}
    if args.onnx:   # what `racklay predict --backend onnx` runs
        from racklay.onnx import export_onnx_bytes, onnx_session

        xn = x.numpy()
        for k, (m, c) in (("shipped, onnxruntime", (shipped, cfg)), ("reference, onnxruntime", (reference, reference.cfg))):
            sess, _ = onnx_session(export_onnx_bytes(m, c), threads=args.threads, source=k)
            feed = {sess.get_inputs()[0].name: xn}
            ort_runners[k] = (lambda s_=sess, f_=feed: s_.run(None, f_))
    if args.memory_format == "channels_last":
        x = x.contiguous(memory_format=torch.channels_last)
        models = {k: m.to(memory_format=torch.channels_last) for k, m in models.items()}

    runners = {k: forward_runner(m, x, bf16) for k, m in models.items()}
    # the shipped model's encoder alone: what the ratio could reach if its decoders cost nothing
    enc_name = "shipped encoder alone"
    runners[enc_name] = forward_runner(shipped.encoder, x, bf16)
    runners.update(ort_runners)
    ort_names = list(ort_runners)
    times = interleaved(runners, args)
    st = {k: summarise(v, 1000.0) for k, v in times.items()}
    names = list(models)

    def row(k):
        return [k, f"{st[k]['wall_median']:.1f} ({st[k]['wall_min']:.1f})", f"{st[k]['cpu_median']:.1f}"]

    def ratio(num, den, label, bold=True):
        """`label`, then st[num] / st[den] as wall median (min) and CPU median."""
        n, d = st[num], st[den]
        wall = f"{n['wall_median'] / d['wall_median']:.2f}x"
        return [label, f"{f'**{wall}**' if bold else wall} (min {n['wall_min'] / d['wall_min']:.2f}x)",
                f"{n['cpu_median'] / d['cpu_median']:.2f}x"]

    rows = [row(names[0]), row(names[1]), ratio(names[1], names[0], "**reference / shipped**")]
    for k in names[2:]:
        rows += [row(k), ratio(k, names[0], f"{k} / shipped")]
    rows += [row(enc_name), ratio(names[1], enc_name, "ceiling: reference / shipped encoder alone", bold=False)]
    if ort_names:
        rows += [row(ort_names[0]), row(ort_names[1]), ratio(ort_names[1], ort_names[0], "**reference / shipped, onnxruntime**")]
    print(f"\nbatch {args.batch} (times per call), both views, input {w}x{h} -> layouts {cfg.layout_size}, {prec}, {args.memory_format}, "
          f"batch norms {'as trained' if args.unfolded else 'folded'}, "
          f"{args.rounds}x{args.calls} interleaved calls per model (target: reference >= 3x slower):")
    print(markdown_table(["model", "wall ms median (min)", "CPU ms median"], rows))
    return 0


if __name__ == "__main__":
    ensure_malloc_env()
    sys.exit(main())
