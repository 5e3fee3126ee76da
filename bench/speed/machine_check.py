"""What kind of machine is this, for the numbers a session is about to measure: the CPU, the
Python interpreter's speed, the first touch of fresh memory against memory used again, and fp32
matrix products. Takes ~10 s.

    .venv/bin/python -m bench.speed.machine_check

Why the memory row: on some VMs a page a process touches for the first time costs ~14 µs (80 MB:
over a second) while the same work on memory already touched takes 25 ms, so WareSynth renders
10x slower than on the same CPU elsewhere and a fast Python loop says nothing about it
(docs/results/2026-11-28-twenty-first-session.md). Compare timings only within one run, and only
with rows of docs/ measured on a machine whose first touch was as fast.
"""
from __future__ import annotations

import os
import platform
import time


def cpu_fields() -> dict[str, str]:
    """The first core's fields of /proc/cpuinfo (`vendor_id`, `model name`, `flags`, ...); empty
    where there is no such file."""
    try:
        with open("/proc/cpuinfo") as f:
            info = f.read()
    except OSError:
        return {}
    fields: dict[str, str] = {}
    for ln in info.splitlines():
        key, sep, value = ln.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    return fields


def cpu_model() -> str:
    fields = cpu_fields()
    if not fields:
        return platform.processor() or "unknown"
    name, family = fields.get("model name", "unknown"), fields.get("cpu family", "?")
    flags = fields.get("flags", "").split()
    extra = ", ".join(f for f in ("avx512f", "avx512_bf16", "amx_bf16") if f in flags) or "no AVX-512"
    return f"{name} (family {family}; {extra})"


def reclaim_daemon() -> bool:
    """True when the kernel's DAMON reclaim thread runs (it hands idle memory back to a VM's host)."""
    for pid in os.listdir("/proc") if os.path.isdir("/proc") else []:
        if pid.isdigit():
            try:
                with open(f"/proc/{pid}/comm") as f:
                    if f.read().startswith("kdamond"):
                        return True
            except OSError:
                pass
    return False


def main() -> int:
    import numpy as np

    print(f"CPU: {cpu_model()}, {os.cpu_count()} logical cores")
    t = time.perf_counter()
    s = 0
    for i in range(3_000_000):
        s += i
    print(f"Python loop, 3 M additions: {time.perf_counter() - t:.2f} s")
    x = np.ones(20_000_000, np.float32)            # 80 MB
    times = []
    for _ in range(3):
        t = time.perf_counter()
        y = x * 2
        times.append(time.perf_counter() - t)
        del y
    print(f"80 MB of new memory (x * 2): first {times[0] * 1e3:.0f} ms, again {min(times[1:]) * 1e3:.0f} ms"
          + ("  <- slow first touch: memory-bound timings here are not comparable" if times[0] > 5 * min(times[1:]) + 0.05 else ""))
    if reclaim_daemon():
        print("kdamond (DAMON memory reclaim) is running: fresh pages stay slow")
    a = np.random.default_rng(0).random((1024, 1024), dtype=np.float32)
    a @ a
    t = time.perf_counter()
    for _ in range(10):
        a @ a
    print(f"fp32 1024^2 matrix products (numpy's BLAS threads): {10 * 2 * 1024 ** 3 / (time.perf_counter() - t) / 1e9:.1f} GFLOP/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
