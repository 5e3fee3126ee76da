"""Numeric precision chosen by the machine, never by a hard-coded default.

bf16 autocast roughly halves CPU time where the CPU computes bf16 natively (AVX512-BF16 or AMX,
e.g. recent Xeons); elsewhere (e.g. AMD EPYC without them) torch emulates it and a training step
is many times slower. On CUDA, bf16 is used where the GPU supports it. `auto` means exactly that,
for training (`TrainConfig.amp`), evaluation and prediction (`--precision`).
"""
from __future__ import annotations

AMP_MODES = ("auto", "none", "bf16")


def native_bf16() -> bool:
    """True when this CPU computes bfloat16 natively (AVX512-BF16 or AMX), where bf16 autocast
    roughly halves inference time (docs/benchmarks.md). Without it bf16 is emulated and slower."""
    try:
        import torch

        return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())
    except Exception:  # noqa: BLE001 - an older/newer torch without these probes: stay in fp32
        return False


def resolve_amp(amp: str, device) -> str:
    """Training autocast: 'auto' -> 'bf16' on a CUDA device with bf16 or a CPU with native bf16,
    else 'none'. 'none' and 'bf16' are taken as given."""
    if amp not in AMP_MODES:
        raise ValueError(f"amp must be one of {AMP_MODES}, got {amp!r}")
    if amp != "auto":
        return amp
    import torch

    dev = torch.device(device)
    if dev.type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported() else "none"
    return "bf16" if native_bf16() else "none"
