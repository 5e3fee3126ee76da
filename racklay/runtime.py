"""Process-wide settings that make torch fast on the machine at hand, applied once by every
command line (`racklay`, `transfer`, `annotate`: `racklay.cli.run`).

glibc's allocator: by default it hands the large, short-lived tensors of a forward / backward
pass back to the kernel after each use (mmap'd chunks, heap trimming) and takes them again on
the next call, paying a page fault for every 4 KiB each time. On the 2-core VMs this project is
built on, that made a training step of the release model (batch 8, 160x256) 1.18x slower and a
`racklay predict` call 1.12x slower (docs/benchmarks.md, "Allocator"). `tune_allocator()` keeps
chunks up to 32 MiB on the heap and up to 1 GiB of freed heap before trimming, from inside the
process, so a pip-installed command gets it without a wrapper script.

The environment variables MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296 (the
Makefile and the benchmarks set them) do a little more: glibc lets only the environment raise
the mmap threshold above 32 MiB, which helps models with larger tensors (the `paper` decoder at
256 px trains 1.14x faster with them than with this function). When they, or GLIBC_TUNABLES,
are set, this function leaves the allocator alone.
"""
from __future__ import annotations

import ctypes
import os
import platform

#: glibc mallopt() parameters (malloc.h) and the values set
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD = 32 * 1024 * 1024        # glibc refuses more (HEAP_MAX_SIZE / 2 on 64-bit)
TRIM_THRESHOLD = 1024 * 1024 * 1024      # mallopt takes a C int
#: set to 1 to leave the allocator alone (e.g. to measure what tuning it buys)
OPT_OUT = "RACKLAY_NO_MALLOPT"
#: the allocator environment the Makefile exports and the benchmarks and tests start processes with
#: (glibc reads it at process start: from inside Python only `tune_allocator` can act)
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": "4294967296", "MALLOC_TRIM_THRESHOLD_": "4294967296"}
#: the user's own glibc settings win
USER_VARS = (*MALLOC_ENV, "GLIBC_TUNABLES")

_applied: str | None = None


def is_glibc() -> bool:
    """True on Linux with glibc, the allocator `tune_allocator` knows how to tune."""
    return platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


def tune_allocator() -> str:
    """Apply the allocator settings once per process. Returns what happened: 'tuned', or why
    not ('opted out', 'user settings', 'not glibc', 'mallopt refused'). Safe to call repeatedly."""
    global _applied
    if _applied is not None:
        return _applied
    if os.environ.get(OPT_OUT) == "1":
        _applied = "opted out"
    elif any(v in os.environ for v in USER_VARS):
        _applied = "user settings"
    elif not is_glibc():
        _applied = "not glibc"
    else:
        try:
            mallopt = ctypes.CDLL(None).mallopt
            mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
            ok = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1 and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
        except (OSError, AttributeError):
            ok = False
        _applied = "tuned" if ok else "mallopt refused"
    return _applied


def exit_on_sigterm() -> None:
    """SIGTERM (`kill`, systemd, docker stop, a scheduler's time limit) becomes a normal exit
    (SystemExit 143) in the main thread, so `finally` blocks and atexit clean-up run: a command
    stopped this way removes its hidden temporary files and folders (racklay.atomic, annotate's
    staged export) as an error or Ctrl-C does, instead of leaving them behind. Every command line
    sets it (`racklay.cli.run`)."""
    import signal
    import sys
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
