"""Training images per second that the data pipeline alone delivers: `racklay train`'s own
DataLoader (RackLayDataset + the augmentation preset, items seeded as in training, uint8 layouts,
OpenCV on one thread per worker) with no model behind it, for several worker counts. Where a GPU waits on its loader (GPU
utilisation near 0 % between bursts), this is the number to raise.

    .venv/bin/python -m bench.speed.loader_speed --data ROOT [--workers 0,2] [--image-size 160x256]
        [--layout-size 256] [--augment paper] [--batch 32] [--batches 20]

It also prints the cost per image split into its steps (image read, layout read and resize,
augmentation, tensors), measured in this process with OpenCV's default threads. Numbers only; nothing is asserted.
"""
from __future__ import annotations

import argparse
import os
import time


def per_step_costs(ds, n: int) -> dict[str, float]:
    """Milliseconds per image of each step of one item, measured in this process through the
    dataset's own steps (`RackLayDataset.prepared_image`, `prepared_layouts`, its transform,
    `image_to_tensor`)."""
    from racklay.torchdata import image_to_tensor

    t = {"read image": 0.0, "read + resize layouts": 0.0, "augment": 0.0, "to tensors": 0.0}
    for k in range(n):
        i = k % len(ds)
        t0 = time.perf_counter()
        img = ds.prepared_image(i)
        t1 = time.perf_counter()
        lays = ds.prepared_layouts(i)
        t2 = time.perf_counter()
        if ds.transform is not None:
            img, lays = ds.transform(img, dict(lays))
        t3 = time.perf_counter()
        image_to_tensor(img)
        t4 = time.perf_counter()
        for key, dt in zip(t, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            t[key] += dt
    return {key: 1e3 * v / n for key, v in t.items()}


def loader_rate(ds, workers: int, batch: int, batches: int, seed: int = 0) -> float:
    """Images per second of the training DataLoader over `batches` batches after one warm-up batch."""
    from racklay.distributed import Batches, Seeded, epoch_batches
    from racklay.torchdata import data_loader

    order = epoch_batches(len(ds), batch, 0, seed, 1, 0)
    need = batches + 1
    order = (order * (need // max(1, len(order)) + 1))[:need]
    sampler = Batches()
    sampler.batches = [[(i, 0) for i in b] for b in order]
    loader = data_loader(Seeded(ds, seed), workers, batch_sampler=sampler)
    it = iter(loader)
    next(it)
    t0 = time.perf_counter()
    n = sum(len(b["id"]) for b in it)
    return n / (time.perf_counter() - t0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="RackLay-format dataset root")
    ap.add_argument("--split", default="train")
    ap.add_argument("--workers", default=f"0,{os.cpu_count() or 1}", help="comma-separated DataLoader worker counts")
    ap.add_argument("--image-size", default="160x256")
    ap.add_argument("--layout-size", type=int, default=256)
    ap.add_argument("--augment", default="paper", choices=["none", "paper", "strong"])
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--batches", type=int, default=20, help="timed batches per worker count")
    args = ap.parse_args()

    from racklay.augment import make_augment
    from racklay.config import image_size_arg
    from racklay.torchdata import RackLayDataset

    ds = RackLayDataset(args.data, args.split, image_size=image_size_arg(args.image_size),
                        layout_size=args.layout_size, transform=make_augment(args.augment, seed=0))
    print(f"{args.data} ({args.split}, {len(ds)} images) -> {args.image_size} input, {args.layout_size}² layouts, "
          f"augment {args.augment}; {os.cpu_count()} CPUs")
    costs = per_step_costs(ds, 40)
    print("one worker, ms per image: " + ", ".join(f"{k} {v:.1f}" for k, v in costs.items())
          + f"; total {sum(costs.values()):.1f}")
    print("| workers | images/s |\n|---|---|")
    for w in (int(x) for x in args.workers.split(",")):
        print(f"| {w} | {loader_rate(ds, w, args.batch, args.batches):.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
