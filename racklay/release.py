"""The shipped model: one weights file inside the package, checked by its sha256 before use.

Commands that run a model (`racklay predict / analyze / eval`, `annotate serve`, `transfer
finetune`) use it when no `--weights` is given. What it was trained on, how, and how well it does:
docs/model-card.md. `make_release` writes such a file from a training checkpoint (fp16 storage,
model weights only, the training facts in its metadata).
"""
from __future__ import annotations

import hashlib
import os
from importlib import resources
from pathlib import Path

#: file name inside racklay/weights/ and its sha256 (docs/model-card.md gives both)
RELEASE_NAME = "racklay-lite0-struct-v11.safetensors"
RELEASE_SHA256 = "8714b6975fabd3037c9c4e36c1dca937a854ccc578e9dfed03d4f5e6cde4e0df"
WEIGHTS_DIR = Path(str(resources.files("racklay") / "weights"))   # package data

_verified: set[str] = set()


def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def release_weights(flag: str = "--weights") -> Path:
    """Path of the shipped weights, after checking the file is there and intact (sha256); `flag`
    is the option that gives another file, named in the errors."""
    path = WEIGHTS_DIR / RELEASE_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the shipped model is missing from this installation; "
                                f"reinstall racklay or pass {flag} FILE")
    key = str(path)
    if key not in _verified:
        got = sha256_file(path)
        if RELEASE_SHA256 and got != RELEASE_SHA256:
            raise ValueError(f"{path}: sha256 {got[:12]}... does not match the release's {RELEASE_SHA256[:12]}... "
                             f"(corrupt or replaced file); reinstall racklay or pass {flag} FILE")
        _verified.add(key)
    return path


def resolve_weights(weights: str | os.PathLike | None, log=None, flag: str = "--weights") -> Path:
    """`--weights` (or `flag`) as given, or the shipped model when it is None (said once through `log`)."""
    if weights:
        return Path(weights)
    path = release_weights(flag)
    if log is not None:
        log(f"using the shipped model {path.name} (docs/model-card.md); {flag} FILE for another")
    return path


def make_release(checkpoint: str | os.PathLike, out: str | os.PathLike, extra: dict | None = None) -> Path:
    """Write a release file from a training checkpoint: model weights in fp16 (BatchNorm counters
    stay integers), the model config, and the checkpoint's training facts plus `extra` as metadata.
    Loading casts back to fp32 (`racklay.checkpoint.load_model`)."""
    import torch

    from .checkpoint import load_checkpoint, save_checkpoint
    from .model import RackLayNet

    ck = load_checkpoint(checkpoint)
    model = RackLayNet(ck.cfg)
    model.load_state_dict(ck.section("model"), strict=True)
    model = model.to(torch.float16)
    meta = {k: ck.meta[k] for k in ("epoch", "val_score", "val", "train_config", "variant", "calibration", "averaged_from",
                                    "averaged_weights", "grafted", "fine_tuned_from", "fine_tuned_on_photos")
            if k in ck.meta}
    meta.update(extra or {})
    meta["storage"] = "fp16"
    return save_checkpoint(out, model, ck.cfg, extra=meta)


def _weighted_sum(checkpoints: list, coefs: list[float], out, meta_from: int, extra: dict) -> Path:
    """Write sum_i coefs[i] x checkpoints[i] (float tensors, BatchNorm statistics included, in
    fp64) as a training-style checkpoint: integer counters, the model config and the training facts
    (`train_config`, whose loss a later fine-tune inherits) from checkpoints[meta_from], plus
    `extra`. Different configs are refused; BatchNorm variances are kept >= 0."""
    from .checkpoint import load_checkpoint, save_checkpoint
    from .model import RackLayNet

    cks = [load_checkpoint(c) for c in checkpoints]
    ref = cks[meta_from]
    for ck in cks:
        if ck.cfg.to_dict() != ref.cfg.to_dict():
            raise ValueError(f"{ck.path}: model config differs from {ref.path}; only one architecture can be combined")
    sds = [ck.section("model") for ck in cks]
    out_sd = {}
    for k, v in sds[meta_from].items():
        if v.is_floating_point():
            v = sum(c * sd[k].double() for c, sd in zip(coefs, sds)).to(v.dtype)
            if k.endswith("running_var"):
                v = v.clamp_min(0)
        out_sd[k] = v
    model = RackLayNet(ref.cfg)
    model.load_state_dict(out_sd, strict=True)
    meta = {k: ref.meta[k] for k in ("train_config", "variant") if k in ref.meta}
    meta.update(extra)
    return save_checkpoint(out, model, ref.cfg, extra=meta)


def average_checkpoints(checkpoints: list, out: str | os.PathLike, weights: list | None = None) -> Path:
    """Write the weight average of checkpoints of one architecture (a "model soup", e.g. a model
    and its own fine-tune) as a training-style checkpoint: float tensors (BatchNorm statistics
    included) averaged in fp64, uniformly or with `weights` (non-negative, normalised to sum 1:
    [0.7, 0.3] moves a model 30 % of the way to its fine-tune); integer counters from the last; the
    model config and the training facts (`train_config`, whose loss a later fine-tune inherits) from
    the last; the sources listed under `averaged_from` (with `averaged_weights`). Different configs
    are refused."""
    if len(checkpoints) < 2:
        raise ValueError("average_checkpoints needs at least two checkpoints")
    w = [1.0] * len(checkpoints) if weights is None else [float(x) for x in weights]
    if len(w) != len(checkpoints) or min(w) < 0 or not sum(w) > 0:
        raise ValueError(f"average_checkpoints: need {len(checkpoints)} non-negative weights with a positive sum, got {weights}")
    w = [x / sum(w) for x in w]
    return _weighted_sum(checkpoints, w, out, -1, {"averaged_from": [str(c) for c in checkpoints], "averaged_weights": w})


def graft_update(base: str | os.PathLike, start: str | os.PathLike, finetuned: str | os.PathLike,
                 out: str | os.PathLike, alpha: float) -> Path:
    """Write base + alpha x (finetuned - start): the change a fine-tune made to `start`, scaled by
    `alpha` and added to `base`, another model trained from `start` ("task arithmetic"). With
    base = start it is the soup `average_checkpoints([start, finetuned], weights=[1 - alpha, alpha])`.
    Used to keep the real-photo fine-tune of an older release when the synthetic training goes on
    from that release. Config and training facts from `base`; the three sources and alpha under
    `grafted`. Different configs are refused."""
    alpha = float(alpha)
    if not 0 <= alpha <= 1:
        raise ValueError(f"graft_update: alpha must be in [0, 1], got {alpha}")
    rec = {"base": str(base), "start": str(start), "finetuned": str(finetuned), "alpha": alpha}
    return _weighted_sum([base, start, finetuned], [1.0, -alpha, alpha], out, 0, {"grafted": rec})


def add_weights_arg(p, what: str = "model checkpoint (.safetensors) or exported .onnx", flag: str = "--weights") -> None:
    """The `--weights` option of every command that runs a model: default the shipped model."""
    p.add_argument(flag, default=None, metavar="FILE",
                   help=f"{what} (default: the shipped model {RELEASE_NAME}, see docs/model-card.md)")


def weights_for_cli(weights: str | os.PathLike | None, quiet: bool = False, flag: str = "--weights") -> str:
    """`--weights` (or `flag`, named in the messages) as a path string: the shipped model when not
    given (said on stderr unless `quiet`), else the file, which must exist (one-line error naming
    it; a run folder given instead points to the weights inside it)."""
    import sys

    path = resolve_weights(weights, log=None if quiet else (lambda m: print(m, file=sys.stderr)), flag=flag)
    if path.is_dir():
        inside = sorted(p.name for p in path.glob("*.safetensors")) + sorted(p.name for p in path.glob("*.onnx"))
        hint = f" (it holds {', '.join(inside[:3])}: give one of them)" if inside else ""
        raise ValueError(f"{path}: {flag} is a folder, not a weights file{hint}")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: weights file not found")
    return str(path)
