"""ONNX export of a RackLay model, checked against torch with onnxruntime.

The exported graph takes `image` (N, 3, H, W) float32, ImageNet-normalised (dynamic batch) and
returns one logits output per view, named after the view: (N, R, 3, S, S). The model config is
stored in the file's metadata (`racklay_model_config`, JSON), so `Predictor("model.onnx")` needs
nothing else. Export uses the TorchScript-based exporter (`dynamo=False`): on this model it is
fast and deterministic; the dynamo exporter is tried only when that one is unavailable.
"""
from __future__ import annotations

import io
import json
import os
import time
import warnings
from pathlib import Path

import numpy as np

from .predict import ONNX_CONFIG_KEY, config_to_dict

DEFAULT_OPSET = 17


def _tuple_outputs(model, views):
    """The model with forward returning a tuple of logits in view order (ONNX has no dicts)."""
    import torch

    class TupleOutputs(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.model = model

        def forward(self, image):
            out = self.model(image)
            return tuple(out[v] for v in views)

    return TupleOutputs().eval()


def export_onnx_bytes(model, cfg, opset: int = DEFAULT_OPSET, batch: int = 1) -> bytes:
    """Serialised ONNX model (with the config in its metadata) for `model` built from `cfg`."""
    import onnx
    import torch

    views = tuple(cfg.views)
    h, w = cfg.input_hw
    wrapped = _tuple_outputs(model, views)
    x = torch.zeros(batch, 3, h, w)
    buf = io.BytesIO()
    kw = dict(input_names=["image"], output_names=list(views), opset_version=opset,
              dynamic_axes={"image": {0: "batch"}, **{v: {0: "batch"} for v in views}})
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TracerWarnings about shape checks that are constant here
        try:
            torch.onnx.export(wrapped, (x,), buf, dynamo=False, **kw)
        except TypeError:  # a torch without the legacy exporter switch
            prog = torch.onnx.export(wrapped, (x,), dynamo=True, input_names=["image"],
                                     output_names=list(views), opset_version=opset,
                                     dynamic_shapes={"image": {0: torch.export.Dim("batch")}})
            prog.save(buf)
    proto = onnx.load_from_string(buf.getvalue())
    entry = proto.metadata_props.add()
    entry.key = ONNX_CONFIG_KEY
    entry.value = json.dumps(config_to_dict(cfg))
    proto.producer_name = "racklay"
    onnx.checker.check_model(proto)
    return proto.SerializeToString()


def export_onnx(model, cfg, out: str | os.PathLike, opset: int = DEFAULT_OPSET) -> Path:
    """Write the ONNX file atomically; returns its path."""
    from .atomic import atomic_write_bytes

    return atomic_write_bytes(out, export_onnx_bytes(model, cfg, opset=opset))


def parity(model, onnx_model, cfg, batch: int = 2, seed: int = 0, image: np.ndarray | None = None) -> dict:
    """Run torch and onnxruntime on the same input; return per view the max |logit difference|,
    the largest |logit| (the scale that difference is relative to), the share of pixels whose
    argmax class differs, and both latencies (ms per call).

    The input is `image` (RGB uint8, any size) if given, else a seeded random normalised batch."""
    import torch

    from .predict import Predictor, _onnx_session

    sess, _ = _onnx_session(onnx_model, source=str(onnx_model) if not isinstance(onnx_model, bytes) else "onnx")
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
    out: dict = {"max_abs_diff": {}, "logit_scale": {}, "class_mismatch": {}, "torch_ms": 1000 * t_torch, "onnx_ms": 1000 * t_onnx,
                 "batch": int(x.shape[0])}
    for v in cfg.views:
        out["max_abs_diff"][v] = float(np.abs(want[v] - got[v]).max())
        out["logit_scale"][v] = float(np.abs(want[v]).max())
        out["class_mismatch"][v] = float((want[v].argmax(2) != got[v].argmax(2)).mean())
    return out
