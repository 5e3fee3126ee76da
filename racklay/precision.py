"""Numeric precision chosen by the machine, never by a hard-coded default: one vocabulary,
`auto` | `fp32` | `bf16`, for training (`TrainConfig.amp`, `--amp`), evaluation and prediction
(`--precision`).

bf16 autocast roughly halves CPU time where the CPU computes bf16 natively (AVX512-BF16 or AMX,
e.g. recent Xeons and Zen 4/5 EPYCs); elsewhere (e.g. a Zen 3 EPYC) torch emulates it and a
training step is many times slower. On CUDA, bf16 is used where the GPU supports it. `auto`
means exactly that. ONNX Runtime always runs fp32.
"""
from __future__ import annotations

PRECISIONS = ("auto", "fp32", "bf16")
#: older spellings still read (training configs written before one vocabulary said `amp: none`)
ALIASES = {"none": "fp32"}
#: what a training flag (`--amp`) accepts: the vocabulary and the older spellings
ACCEPTED = (*PRECISIONS, *ALIASES)


def native_bf16() -> bool:
    """True when this CPU computes bfloat16 natively (AVX512-BF16 or AMX), where bf16 autocast
    roughly halves inference time (docs/benchmarks.md). Without it bf16 is emulated and slower."""
    try:
        import torch

        return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())
    except Exception:  # noqa: BLE001 - an older/newer torch without these probes: stay in fp32
        return False


def check_precision(precision: str, what: str = "precision") -> str:
    """The precision in the one vocabulary (an older spelling translated); a one-line error
    naming the allowed values otherwise."""
    precision = ALIASES.get(precision, precision)
    if precision not in PRECISIONS:
        raise ValueError(f"{what} must be one of {PRECISIONS}, got {precision!r}")
    return precision


def resolve_precision(precision: str, device="cpu", backend: str = "torch") -> str:
    """'auto' -> 'bf16' where `device` computes it natively (a CUDA GPU with bf16; a CPU with
    AVX512-BF16 or AMX, torch backend only), else 'fp32'. 'fp32' and 'bf16' are taken as given."""
    precision = check_precision(precision)
    if precision != "auto":
        return precision
    if backend != "torch":
        return "fp32"
    import torch

    if torch.device(device).type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported() else "fp32"
    return "bf16" if native_bf16() else "fp32"


def cast_for_autocast(model) -> int:
    """For inference under bf16 autocast only: keep the weight and bias of every convolution and
    linear layer in bfloat16, which autocast would otherwise cast from fp32 on every call (bf16
    autocast runs those layers in bf16 whatever their weights' dtype, so the logits are bit for
    bit the same; a model with the brightness cue, `--struct-cue`, subtracts that layer's bias
    once more outside it, now at its bf16 rounding: the gap logit moves by at most that). On a
    2-core Xeon with AMX the shipped model ran 1.16x faster, the reference architecture
    1.27-1.29x (docs/benchmarks.md, "Weights kept in bf16"). The model must then always run under bf16
    autocast (`racklay.predict.Predictor` does). Returns how many layers it cast."""
    import torch
    from torch import nn

    n = 0
    for mod in model.modules():
        if isinstance(mod, (nn.Linear, nn.modules.conv._ConvNd)):
            mod.to(torch.bfloat16)
            n += 1
    return n
