"""`racklay export`'s engine: write a RackLay model as ONNX (`racklay.onnx`, where the graph and
its metadata are described) and check the file against torch with onnxruntime (`parity`).
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from .onnx import DEFAULT_OPSET, export_onnx_bytes, onnx_session


def export_onnx(model, cfg, out: str | os.PathLike, opset: int = DEFAULT_OPSET) -> Path:
    """Write the ONNX file atomically; returns its path."""
    from .atomic import atomic_write_bytes

    return atomic_write_bytes(out, export_onnx_bytes(model, cfg, opset=opset))


def parity(model, onnx_model, cfg, batch: int = 2, seed: int = 0, image: np.ndarray | None = None) -> dict:
    """Run torch and onnxruntime on the same input; return per view the max |logit difference|,
    the largest |logit| (the scale that difference is relative to), the share of pixels whose
    argmax class differs, the max |probability difference|, and both latencies (ms per call).

    The input is `image` (RGB uint8, any size) if given, else a seeded random normalised batch."""
    import torch

    from .predict import Predictor

    sess, _ = onnx_session(onnx_model, source=str(onnx_model) if not isinstance(onnx_model, bytes) else "onnx")
    ref = Predictor.from_model(model, cfg)
    if image is not None:
        x = ref.prepare(image)
    else:
        h, w = cfg.input_hw
        x = torch.from_numpy(np.random.default_rng(seed).standard_normal((batch, 3, h, w), dtype=np.float32))
    t0 = time.perf_counter()
    want = ref.logits(x)
    t_torch = time.perf_counter() - t0
    t0 = time.perf_counter()
    got = dict(zip(cfg.views, sess.run(list(cfg.views), {"image": x.numpy()})))
    t_onnx = time.perf_counter() - t0
    from .predict import softmax_classes

    out: dict = {"max_abs_diff": {}, "logit_scale": {}, "class_mismatch": {}, "max_prob_diff": {}, "torch_ms": 1000 * t_torch, "onnx_ms": 1000 * t_onnx,
                 "batch": int(x.shape[0])}
    for v in cfg.views:
        out["max_abs_diff"][v] = float(np.abs(want[v] - got[v]).max())
        out["logit_scale"][v] = float(np.abs(want[v]).max())
        out["class_mismatch"][v] = float((want[v].argmax(2) != got[v].argmax(2)).mean())
        out["max_prob_diff"][v] = float(np.abs(softmax_classes(want[v], 2) - softmax_classes(got[v], 2)).max())
    return out
