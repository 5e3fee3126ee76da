"""How the training processes share the work and the randomness: torchrun's process group
(`Dist`: one process without it), the global seeds, per-sample seeds of the transform (`Seeded`:
items addressed as (index, epoch)), and each process's batches of an epoch (`epoch_batches`,
reshuffled per epoch by `Batches` without restarting the DataLoader workers). The order of
samples in epoch e is a pure function of (seed, e), so a resumed run sees what an uninterrupted
one would have."""
from __future__ import annotations

import os
import random

import numpy as np
import torch


class Dist:
    """Process-group facts from torchrun's environment (a single process without it)."""

    def __init__(self, device_pref: str):
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        self.local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        cuda = torch.cuda.is_available() and device_pref in ("auto", "cuda")
        if device_pref == "cuda" and not torch.cuda.is_available():
            raise ValueError("device 'cuda' requested but torch sees no GPU")
        self.device = torch.device(f"cuda:{self.local_rank}" if cuda else "cpu")
        self.enabled = self.world > 1
        if self.enabled and not torch.distributed.is_initialized():
            if cuda:
                torch.cuda.set_device(self.device)
            torch.distributed.init_process_group("nccl" if cuda else "gloo")

    @property
    def main(self) -> bool:
        return self.rank == 0

    def barrier(self):
        if self.enabled:
            torch.distributed.barrier()

    def broadcast_flag(self, flag: bool) -> bool:
        """Rank 0's decision, shared with every process."""
        if not self.enabled:
            return flag
        t = torch.tensor([1 if flag else 0], dtype=torch.int64, device=self.device)
        torch.distributed.broadcast(t, 0)
        return bool(t.item())

    def mean(self, values: list[float]) -> list[float]:
        if not self.enabled:
            return values
        t = torch.tensor(values, dtype=torch.float64, device=self.device)
        torch.distributed.all_reduce(t)
        return (t / self.world).tolist()

    def close(self):
        if self.enabled and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()


def sample_seed(seed: int, epoch: int, index: int) -> int:
    return int(np.random.SeedSequence([seed, epoch, index]).generate_state(1)[0])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


class Seeded(torch.utils.data.Dataset):
    """Items addressed as (index, epoch); the transform's randomness is seeded per item."""

    def __init__(self, base, seed: int):
        self.base, self.seed = base, seed

    def __len__(self):
        return len(self.base)

    def __getitem__(self, key):
        i, epoch = key
        s = sample_seed(self.seed, epoch, i)
        t = self.base.transform
        if t is not None:
            seed_everything(s)
            for meth in ("reseed", "set_random_seed"):
                if callable(getattr(t, meth, None)):
                    getattr(t, meth)(s)
                    break
        item = getattr(self.base, "item", None)   # ReplayMix: which replay samples depends on the epoch
        return item(i, epoch) if item is not None else self.base[i]


class Batches:
    """A batch sampler whose batches are replaced before each epoch (lets persistent workers
    live across epochs)."""

    def __init__(self):
        self.batches: list = []

    def __iter__(self):
        return iter(list(self.batches))

    def __len__(self):
        return len(self.batches)


def epoch_batches(n: int, batch_size: int, epoch: int, seed: int, world: int, rank: int) -> list[list[int]]:
    """This process's batches of epoch `epoch`: a DistributedSampler permutation seeded by
    (seed, epoch), cut into batches (a last batch of one sample is dropped: BatchNorm)."""
    from torch.utils.data.distributed import DistributedSampler

    sampler = DistributedSampler(range(n), num_replicas=world, rank=rank, shuffle=True, seed=seed)
    sampler.set_epoch(epoch)
    idx = list(sampler)
    batches = [idx[i:i + batch_size] for i in range(0, len(idx), batch_size)]
    if len(batches) > 1 and len(batches[-1]) < 2:
        batches.pop()
    return batches


__all__ = ["Dist", "sample_seed", "seed_everything", "Seeded", "Batches", "epoch_batches"]
