"""ONNX in and out: a RackLay model as ONNX bytes, and an onnxruntime session from such a file.

The exported graph takes `image` (N, 3, H, W) float32, ImageNet-normalised (dynamic batch) and
returns one logits output per view, named after the view: (N, R, 3, S, S). The model config is
stored in the file's metadata (`racklay_model_config`, `ModelConfig.to_dict` as JSON) and read
back strictly with `ModelConfig.from_dict`: a file whose config has a key this version does not
know is refused with one line (re-export it with this version's `racklay export`). Export uses the
TorchScript-based exporter (`dynamo=False`): on this model it is fast and deterministic; the
dynamo exporter is tried only when that one is unavailable.

Depends on racklay.model only; `racklay.predict` (the onnx backend) and `racklay.export` (the
command, with its torch/onnxruntime parity check) build on it.
"""
from __future__ import annotations

import io
import json
import warnings
from pathlib import Path

#: metadata key under which the model config is stored in the ONNX file
ONNX_CONFIG_KEY = "racklay_model_config"
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
    entry.value = json.dumps(cfg.to_dict())
    proto.producer_name = "racklay"
    onnx.checker.check_model(proto)
    return proto.SerializeToString()


def onnx_session(model, threads: int | None = None, source: str | None = None):
    """(onnxruntime session, ModelConfig) for an ONNX file path or its bytes. `source` names the
    model in error messages (default: the path)."""
    import onnxruntime as ort

    from .config import ModelConfig  # no torch: an ONNX session needs none

    src = source or str(model)
    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = int(threads)
    opts.log_severity_level = 3
    try:
        payload = model if isinstance(model, (bytes, bytearray)) else str(model)
        if not isinstance(model, (bytes, bytearray)) and not Path(model).is_file():
            raise FileNotFoundError(f"{src}: ONNX file not found")
        sess = ort.InferenceSession(payload, sess_options=opts, providers=["CPUExecutionProvider"])
    except FileNotFoundError:
        raise
    except Exception as e:  # onnxruntime raises its own exception types
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"{src}: not a loadable ONNX model ({msg})") from None
    meta = sess.get_modelmeta().custom_metadata_map
    if ONNX_CONFIG_KEY not in meta:
        raise ValueError(f"{src}: ONNX file has no RackLay model config (export it with `racklay export`)")
    try:
        cfg = ModelConfig.from_dict(json.loads(meta[ONNX_CONFIG_KEY]))
    except (ValueError, TypeError) as e:
        raise ValueError(f"{src}: bad RackLay model config in the ONNX metadata ({e}); "
                         "re-export it with this version's `racklay export`") from None
    return sess, cfg
