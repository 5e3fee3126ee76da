"""racklay export --weights W --onnx out.onnx"""
from __future__ import annotations

from racklay.config import positive_float


def register(sub) -> None:
    p = sub.add_parser(
        "export", help="export a trained model to ONNX (checked against torch)",
        description="Export a checkpoint to ONNX: input `image` (N, 3, H, W) float32 ImageNet-normalised, "
                    "one logits output per view (N, R, 3, S, S), dynamic batch, the model config in the "
                    "file's metadata. The file is then run with onnxruntime beside torch on the same input "
                    "and the maximum absolute logit difference is printed (and checked against --tol). "
                    "Use it with `racklay predict --weights out.onnx` or `--backend onnx`.")
    p.add_argument("--weights", required=True, help="model checkpoint (.safetensors)")
    p.add_argument("--onnx", required=True, help="output .onnx file")
    p.add_argument("--opset", type=int, default=17, help="ONNX opset (default 17)")
    p.add_argument("--image", default=None, help="check parity on this photo instead of a random batch")
    p.add_argument("--tol", type=positive_float, default=1e-4,
                   help="fail (exit 1) when max |logit difference| exceeds TOL x max(1, max |logit|) "
                        "(default 1e-4: float32 rounding over a deep network, not a real mismatch). A struct "
                        "model draws sharp shelf and box edges, where a float32 difference in a length moves "
                        "an edge pixel's logit far: it is checked instead on argmax agreement (at most "
                        "0.01%% of pixels differ) and on probabilities (max difference <= 100 x TOL)")
    p.add_argument("--no-check", action="store_true", help="skip the onnxruntime parity check")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from racklay.checkpoint import load_model
    from racklay.commands import CLIError
    from racklay.export import export_onnx, parity

    if not Path(args.weights).is_file():
        raise CLIError(f"{args.weights}: weights file not found")
    if Path(args.onnx).suffix.lower() != ".onnx":
        raise CLIError(f"{args.onnx}: output name must end in .onnx")
    image = None
    if args.image and not args.no_check:
        from racklay.data import read_image
        image = read_image(args.image)   # checked before anything is written
    model, cfg, _ = load_model(args.weights, map_location="cpu")
    model.eval()
    try:
        path = export_onnx(model, cfg, args.onnx, opset=args.opset)
    except (OSError, ValueError):
        raise
    except Exception as e:  # the exporter's own errors (e.g. an opset it cannot target)
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise CLIError(f"{args.onnx}: ONNX export at opset {args.opset} failed: {first}") from None
    size_mb = path.stat().st_size / 1e6
    print(f"exported {args.weights} -> {path} ({size_mb:.1f} MB, opset {args.opset}, views {'/'.join(cfg.views)})")
    if args.no_check:
        return 0
    res = parity(model, path, cfg, image=image)
    if cfg.decoder == "struct":     # sharp edges: logits are ill-conditioned there, layouts are not
        worst = max(max(res["max_prob_diff"][v] / 100, res["class_mismatch"][v]) for v in cfg.views)
    else:
        worst = max(res["max_abs_diff"][v] / max(1.0, res["logit_scale"][v]) for v in cfg.views)
    for v in cfg.views:
        print(f"  {v}: max abs logit difference onnxruntime vs torch = {res['max_abs_diff'][v]:.3g} "
              f"(logits up to {res['logit_scale'][v]:.3g}), argmax differs on "
              f"{100 * res['class_mismatch'][v]:.4f}% of pixels, max probability difference "
              f"{res['max_prob_diff'][v]:.3g}")
    print(f"  batch {res['batch']}: torch {res['torch_ms']:.0f} ms, onnxruntime {res['onnx_ms']:.0f} ms (one call, cold)")
    if worst > args.tol:
        path.unlink(missing_ok=True)
        print(f"parity check FAILED: relative difference {worst:.3g} > --tol {args.tol}; {path} removed "
              "(--no-check keeps an unchecked export)")
        return 1
    print(f"parity OK (relative difference {worst:.3g} <= {args.tol})")
    return 0
