"""Helpers shared by the test files (import them: `from conftest import REPO, make_toy`).

Slow tests (more than ~10 s on 2 CPU cores) carry `@pytest.mark.slow`: `pytest -m "not slow"`
runs the fast subset in a few minutes; plain `pytest` runs everything."""
from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

from racklay.runtime import MALLOC_ENV

REPO = Path(__file__).resolve().parents[1]
#: the 21 real photos (an annotation project with their labels)
REAL_PHOTOS = REPO / "datasets" / "real-photos"
#: glibc's allocator settings the Makefile uses (they halve torch step times on this kind of VM)
ENV = {**os.environ, **MALLOC_ENV}


@pytest.fixture(autouse=True)
def _default_sigterm():
    """A command line run in this process (racklay.cli.run) turns SIGTERM into SystemExit; put the
    default back after each test, so a CI time limit's SIGTERM still ends pytest."""
    import signal

    yield
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


@pytest.fixture(autouse=True)
def _seeded_global_rngs():
    """Every test starts from the same global torch / numpy random state, so what it builds at
    random (an initialised model, a noise image) does not depend on which tests ran before it or
    on a `-k` selection."""
    import numpy as np
    import torch

    torch.manual_seed(0)
    np.random.seed(0)


def make_toy(tmp_path_factory, n: int, seed: int, name: str = "toy", **kw) -> Path:
    """A schematic RackLay-format dataset (racklay.toy) of `n` samples in a fresh temporary
    folder; `kw` goes to build_toy_dataset (R, D, ...)."""
    from racklay.toy import build_toy_dataset

    root = tmp_path_factory.mktemp(name) / "ds"
    build_toy_dataset(root, n=n, seed=seed, **kw)
    return root


def run_module(module: str, *args, env=None, timeout: float = 300, cwd=None) -> subprocess.CompletedProcess:
    """`python -m MODULE ARGS` in a child process (text output captured)."""
    return subprocess.run([sys.executable, "-m", module, *map(str, args)], env=env or ENV, capture_output=True,
                          text=True, timeout=timeout, cwd=cwd)


def metrics_rows(run: Path) -> list[dict]:
    """A training run's metrics.csv as a list of rows (strings)."""
    with open(Path(run) / "metrics.csv") as f:
        return list(csv.DictReader(f))



def ground_truth_net(items, lut):
    """A stand-in model (torch Module) that returns fixed logits for the ground truth of whichever
    dataset image it is given (found by the image tensor's hash): `lut[k]` are the 3 logits of a
    pixel whose true class is k. `items` are RackLayDataset samples. Exercises scoring and
    decision code without training."""
    import hashlib

    import torch

    def key(x):
        return hashlib.sha1(x.numpy().tobytes()).hexdigest()

    class GroundTruthNet(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.table = {key(it["image"]): {v: it[v] for v in ("top", "front")} for it in items}
            self.lut = torch.as_tensor(lut, dtype=torch.float32)

        def forward(self, x):
            out = {}
            for v in ("top", "front"):
                gt = torch.stack([self.table[key(xi)][v] for xi in x]).long()   # (N, R, S, S)
                out[v] = self.lut[gt].permute(0, 1, 4, 2, 3).contiguous()       # (N, R, 3, S, S)
            return out

    return GroundTruthNet()
