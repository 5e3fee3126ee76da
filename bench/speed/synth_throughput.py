"""WareSynth throughput: generate N images of a recipe (default: 300 x complex at 470x280)
with everything written (RGB, layouts, depth, normals, semantic, instance, KITTI, meta, COCO,
splits), then print images/min, the per-stage breakdown and the ratio to WareSynth's 80/min
(Blender on an RTX 2080Ti, paper Sec. 3).

    .venv/bin/python -m bench.speed.synth_throughput --n 300 --workers 2

Stage times are wall seconds measured inside each worker (summed over workers, per image);
with K workers on K cores they add up to about K x the wall time per image. The machine's
load average is printed because the numbers depend on what else runs. Each run writes ~2.3 MB
per image; on a VM whose fresh memory is slow to touch once the page cache is full
(`bench/speed/machine_check.py` says so), the same run swings by ±20 %: compare runs made back to
back, ideally each after `sync; echo 3 > /proc/sys/vm/drop_caches` (root).
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

WARESYNTH_PER_MIN = 80.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recipe", default="complex")
    ap.add_argument("--n", type=int, default=300)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--lp-threads", type=int, default=None,
                    help="LP_NUM_THREADS per worker (default: the generator's, 0 with --workers > 1)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="output folder (default: a temporary one, removed afterwards)")
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args(argv)

    from racklay.synth.generate import STAGES, generate_dataset, lp_threads_for
    from racklay.synth.recipe import load_recipe

    recipe = load_recipe(args.recipe, args.set)
    tmp = None
    out = args.out
    if out is None:
        tmp = tempfile.mkdtemp(prefix="synth_bench_")
        out = os.path.join(tmp, "ds")
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    res = generate_dataset(recipe, args.n, out, seed=args.seed, workers=args.workers, lp_threads=args.lp_threads,
                           progress=True)
    wall = time.perf_counter() - t0
    load1 = os.getloadavg()
    lp = lp_threads_for(args.lp_threads, args.workers)
    lp = lp if lp is not None else os.environ.get("LP_NUM_THREADS", "llvmpipe's default")
    ru = resource.getrusage(resource.RUSAGE_CHILDREN), resource.getrusage(resource.RUSAGE_SELF)
    cpu = sum(r.ru_utime + r.ru_stime for r in ru)
    n = len(res.generated)
    size = sum(p.stat().st_size for p in Path(out).rglob("*") if p.is_file())
    rate = n / wall * 60
    print(f"\nWareSynth throughput: recipe {recipe.name}, {recipe.image_width}x{recipe.image_height}, "
          f"{n} images, {args.workers} worker(s) x LP_NUM_THREADS={lp}, "
          f"layouts {recipe.R}x{recipe.layout_size}^2 x 2 views")
    print(f"  wall {wall:.1f} s (incl. start-up and finalize)  ->  {rate:.0f} images/min  "
          f"({rate / WARESYNTH_PER_MIN:.1f}x WareSynth's {WARESYNTH_PER_MIN:.0f}/min)")
    print(f"  CPU time {cpu:.1f} s = {cpu / max(n, 1) * 1000:.0f} ms/image  "
          f"(-> {60 / (cpu / max(n, 1)) * os.cpu_count():.0f} images/min if {os.cpu_count()} cores were ours alone)")
    print(f"  load average before {load0[0]:.1f}, after {load1[0]:.1f} on {os.cpu_count()} cores (shared machine)")
    print(f"  dataset on disk: {size / 1e6:.0f} MB ({size / max(n, 1) / 1e6:.2f} MB/image)")
    tot = sum(res.timings.get(s, 0.0) for s in STAGES)
    ctot = sum(res.timings.get("cpu_" + s, 0.0) for s in STAGES)
    print("  per-stage time inside the workers, ms/image (share):   wall            CPU (process, incl. llvmpipe)")
    for s in STAGES:
        v, c = res.timings.get(s, 0.0), res.timings.get("cpu_" + s, 0.0)
        print(f"    {s:12s}                                  {v / max(n, 1) * 1000:7.1f} ({100 * v / max(tot, 1e-9):4.1f}%)"
              f"   {c / max(n, 1) * 1000:7.1f} ({100 * c / max(ctot, 1e-9):4.1f}%)")
    print(f"    {'total':12s}                                  {tot / max(n, 1) * 1000:7.1f}          "
          f"{ctot / max(n, 1) * 1000:7.1f}")
    if tmp:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
