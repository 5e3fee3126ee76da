"""WareSynth throughput of this checkout against another revision, run for run.

    .venv/bin/python -m bench.speed.synth_pairs --baseline 6a8e3d5 --recipe mixed --recipe pallet [--pairs 2]

On a shared VM the same `synth_throughput` command swings by ±20 % and more from one run to the
next (`bench/speed/machine_check.py`), so a speed-up is only readable from runs made back to back.
This script checks the baseline revision out into a temporary git worktree and alternates
`bench.speed.synth_throughput` runs of the baseline and of this checkout (same Python, same
arguments, the code on `PYTHONPATH`), dropping the page cache before each run when it may (root;
`--no-drop-caches` to skip), and prints images/min and CPU ms per image of every run, the ratio of
each pair and the median ratio per recipe. Run it with nothing else on the machine.
"""
from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.common import REPO, markdown_table


def drop_caches() -> bool:
    """Flush dirty pages and drop the page cache (root only); False where not allowed."""
    try:
        os.sync()
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
        return True
    except OSError:
        return False


def run_once(tree: Path, recipe: str, n: int, workers: int) -> tuple[float, float]:
    """One `synth_throughput` run of the code in `tree`: (images/min, CPU ms per image)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    cmd = [sys.executable, "-m", "bench.speed.synth_throughput", "--recipe", recipe, "--n", str(n),
           "--workers", str(workers)]
    out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    rate = re.search(r"(\d+) images/min", out.stdout)
    cpu = re.search(r"= (\d+) ms/image", out.stdout)
    if out.returncode or not rate or not cpu:
        tail = (out.stderr or out.stdout).strip().splitlines()[-1:] or ["no output"]
        raise SystemExit(f"synth_throughput failed in {tree} (recipe {recipe}): {tail[0]}")
    return float(rate.group(1)), float(cpu.group(1))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True, help="git revision to compare against (a commit, tag or branch)")
    ap.add_argument("--recipe", action="append", default=None, help="recipe to run (repeatable; default mixed)")
    ap.add_argument("--pairs", type=int, default=2, help="baseline/current pairs per recipe (default 2)")
    ap.add_argument("--n", type=int, default=300, help="images per run (default 300)")
    ap.add_argument("--workers", type=int, default=2, help="worker processes per run (default 2)")
    ap.add_argument("--no-drop-caches", action="store_true", help="do not drop the page cache before each run")
    args = ap.parse_args(argv)
    if args.pairs < 1 or args.n < 1 or args.workers < 1:
        ap.error("--pairs, --n and --workers must be at least 1")
    recipes = args.recipe or ["mixed"]
    rev = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{args.baseline}^{{commit}}"], cwd=REPO,
                         capture_output=True, text=True).stdout.strip()
    if not rev:
        ap.error(f"--baseline {args.baseline!r}: not a commit of {REPO}")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    if subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True,
                      text=True).stdout.strip():
        head += ", with uncommitted changes"
    with tempfile.TemporaryDirectory(prefix="synth_pairs_") as tmp:
        base = Path(tmp) / "baseline"
        subprocess.run(["git", "worktree", "add", "--detach", "--quiet", str(base), rev], cwd=REPO, check=True)
        try:
            rows, dropped = [], True
            for recipe in recipes:
                for k in range(args.pairs):
                    pair = {}
                    for side, tree in (("baseline", base), ("current", REPO)):
                        if not args.no_drop_caches:
                            dropped &= drop_caches()
                        pair[side] = run_once(tree, recipe, args.n, args.workers)
                        print(f"{recipe} pair {k + 1} {side}: {pair[side][0]:.0f} images/min, "
                              f"{pair[side][1]:.0f} CPU ms/image", flush=True)
                    rows.append((recipe, k + 1, pair["baseline"], pair["current"]))
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=REPO, check=False)
    print(f"\nWareSynth throughput, baseline {rev[:7]} vs this checkout ({head}), "
          f"{args.n} images x {args.workers} workers per run, runs alternated"
          + ("" if args.no_drop_caches or dropped else " (page cache not dropped: not root)"))
    print("\n" + markdown_table(
        ["recipe", "pair", "baseline images/min (CPU ms)", "current images/min (CPU ms)", "current / baseline"],
        [[recipe, k, f"{b:.0f} ({bc:.0f})", f"{c:.0f} ({cc:.0f})", f"{c / b:.2f}x"]
         for recipe, k, (b, bc), (c, cc) in rows]))
    for recipe in recipes:
        ratios = [c[0] / b[0] for r, _, b, c in rows if r == recipe]
        print(f"{recipe}: median ratio {statistics.median(ratios):.2f}x over {len(ratios)} pair(s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
