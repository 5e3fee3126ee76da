"""Shared helpers of the benchmarks in bench/ (not part of the installed package). Every
benchmark runs from the repository root as a module: `python -m bench.speed.train_speed`.

glibc's allocator dominates torch on this kind of VM (measured here: a reference training
step at 256 px fell from 7.2 s to 3.7 s with these settings). The variables are read by glibc
when the process starts, so setting them from Python is too late: `ensure_malloc_env()`
re-executes the script with them set unless they already are (the Makefile exports them too).
"""
from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from pathlib import Path

from racklay.runtime import MALLOC_ENV  # the one home of the allocator settings

#: the repository root (datasets/, docs/img/ are found from here)
REPO = Path(__file__).resolve().parents[1]

#: the paper's best row of Table 1 (RackLay-D-disc on its `complex` test set, paper-protocol mIoU %):
#: what the reproduction row is compared with
PAPER_ROW = {"top rack": 93.15, "top box": 95.07, "front rack": 90.75, "front box": 94.29}
#: the model issue's dataset-level box IoU target (%) for the same reproduction row
REPRODUCTION_BOX_TARGET = {"top": 70.0, "front": 75.0}


def ensure_malloc_env() -> None:
    """Re-exec this script with the MALLOC_* variables set (once), unless disabled with
    RACKLAY_BENCH_NO_MALLOC=1 (to measure the difference)."""
    if os.environ.get("RACKLAY_BENCH_NO_MALLOC") == "1":
        return
    missing = {k: v for k, v in MALLOC_ENV.items() if k not in os.environ}
    if missing:
        os.environ.update(missing)
        spec = getattr(sys.modules["__main__"], "__spec__", None)   # run as `python -m bench...`
        argv = ["-m", spec.name, *sys.argv[1:]] if spec else sys.argv
        os.execv(sys.executable, [sys.executable, *argv])


def conditions() -> str:
    """One line describing the machine and load, printed with every result."""
    import torch

    load = os.getloadavg()
    malloc = "set" if all(k in os.environ for k in MALLOC_ENV) else "NOT set"
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
            f"{torch.get_num_threads()} threads, MALLOC_* {malloc}, nice {os.nice(0)}, "
            f"load average {load[0]:.1f}/{load[1]:.1f}/{load[2]:.1f} (CPU shared with other jobs)")


def time_calls(fn, n: int) -> list[tuple[float, float]]:
    """(wall-clock seconds, process CPU seconds) of each of n calls of fn(). On a shared machine
    the CPU time (with --threads 1) is the cost least disturbed by other processes: waiting for a
    core does not count, only the work itself (and cache effects) do."""
    out = []
    for _ in range(n):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0, time.process_time() - c0))
    return out


def median(xs) -> float:
    return statistics.median(xs)


def summarise(samples: list[tuple[float, float]], scale: float = 1.0) -> dict:
    """Median and minimum wall time and median CPU time of (wall, cpu) samples, times `scale`."""
    wall = [w * scale for w, _ in samples]
    cpu = [c * scale for _, c in samples]
    return {"wall_median": median(wall), "wall_min": min(wall), "cpu_median": median(cpu),
            "wall": wall, "cpu": cpu}


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def add_common_args(ap, rounds: int = 3, calls: int = 5, warmup: int = 2) -> None:
    """Options shared by the benchmarks: interleaving, threads, JSON output."""
    ap.add_argument("--rounds", type=int, default=rounds, help=f"interleaved rounds (default {rounds})")
    ap.add_argument("--calls", type=int, default=calls, help=f"timed calls per model per round (default {calls})")
    ap.add_argument("--warmup", type=int, default=warmup, help=f"untimed calls per model first (default {warmup})")
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    ap.add_argument("--json", default=None, help="also write the raw numbers here")


def start(args) -> None:
    """Apply --threads and print the conditions line."""
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    print("conditions:", conditions(), flush=True)


def interleaved(runners: dict, args) -> dict:
    """Time every runner: `warmup` untimed calls each, then `rounds` rounds in which each runner
    makes `calls` timed calls in turn (so background load hits all alike).
    -> {key: [(wall s, cpu s), ...]}"""
    for fn in runners.values():
        time_calls(fn, args.warmup)
    times = {k: [] for k in runners}
    for _ in range(args.rounds):
        for k, fn in runners.items():
            times[k] += time_calls(fn, args.calls)
    return times


def add_batch_arg(ap, help_extra: str = "") -> None:
    """--batch N (images per forward call, >= 1, default 1) for the inference benchmarks."""
    from racklay.config import at_least

    ap.add_argument("--batch", type=at_least(1), default=1, help="images per call (default 1" + help_extra + ")")


def reference_model(cfg):
    """The speed target's reference architecture (ResNet-18 + the authors' `paper` decoder) at a
    model config's input size, layout size, views and R, randomly initialised (seeded; weights
    do not change the cost), in eval mode."""
    import torch

    from racklay.model import ModelConfig, RackLayNet

    torch.manual_seed(0)
    return RackLayNet(ModelConfig(image_size=cfg.image_size, layout_size=cfg.layout_size, views=cfg.views,
                                  R=cfg.R, encoder="resnet18", decoder="paper")).eval()


def forward_runner(model, x, bf16: bool):
    """A no-argument call that runs `model(x)` as `racklay predict` does (inference mode; when
    `bf16`, bf16 autocast with the model's convolution and linear weights cast to bf16 once, here:
    `racklay.precision.cast_for_autocast`), for `interleaved`. Build every other use of the model
    (an ONNX export, an fp32 run) before this."""
    import torch

    if bf16:
        from racklay.precision import cast_for_autocast

        cast_for_autocast(model)

    def f():
        with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            model(x)
    return f


def labelled_photos(project, split: str = "all", limit: int | None = None) -> list[str]:
    """The finished photos of an annotate project (`annotate.store.Project`), those of `split` in
    its SOURCES.tsv unless split is `all`; the first `limit` of them."""
    from annotate.dataset import read_split_file
    from annotate.store import DONE_STATUSES

    names = [n for n in project.images() if (project.read_annotation(n) or {}).get("status") in DONE_STATUSES]
    if split != "all":
        src = project.root / "SOURCES.tsv"
        if not src.is_file():
            raise SystemExit(f"{src}: missing, so no split to select --split {split} by (use --split all)")
        split_of = read_split_file(src)
        names = [n for n in names if split_of.get(n) == split]
    if not names:
        raise SystemExit(f"{project.root}: no finished photo{'' if split == 'all' else f' in split {split}'}")
    return names[:limit]


def add_struct_split_args(ap, data_help: str = "RackLay dataset root") -> None:
    """The inputs of the benches that read a struct model's structures on a dataset split:
    --weights, --data, --split, --n (the split's first N images), --batch-size, --precision."""
    from racklay.predict import add_precision_args

    ap.add_argument("--weights", default=None, help="a struct model (default: the shipped one)")
    ap.add_argument("--data", required=True, help=data_help)
    ap.add_argument("--split", default="test")
    ap.add_argument("--n", type=int, default=400, help="the split's first N images (default 400)")
    ap.add_argument("--batch-size", type=int, default=8)
    add_precision_args(ap)


def open_struct_split(args):
    """(Predictor, dataset root, views, dataset of the split's first N images) for the arguments
    of `add_struct_split_args`; one line and exit for a model without a structure."""
    from racklay.evaluate import split_dataset
    from racklay.predict import Predictor
    from racklay.release import resolve_weights

    pred = Predictor(resolve_weights(args.weights), precision=args.precision)
    if pred.cfg.decoder != "struct":
        raise SystemExit(f"{pred.weights}: the {pred.cfg.decoder} decoder has no structure; give a struct model")
    return (pred, *split_dataset(pred, args.data, args.split, args.n))


def table1_header(first: str, views) -> str:
    """The header row of a table of `table1_cells`, after `first` column(s) ("structure", "images | n")."""
    return (f"| {first} | " + " | ".join(f"{v} {c} mIoU" for v in views for c in ("rack", "box"))
            + " | " + " | ".join(f"{v} {k} IoU" for v in views for k in ("shelf", "box")) + " |\n"
            + "|---" * (first.count("|") + 1 + 4 * len(views)) + "|")


def table1_cells(result: dict, views) -> list[float]:
    """A `racklay.metrics.LayoutMetrics` result -> x100: per view the paper-protocol rack and box
    mIoU, then per view the dataset-level shelf and box IoU."""
    return ([100 * result[v]["paper"][c]["mIoU"] for v in views for c in ("rack", "box")]
            + [100 * result[v]["dataset"][k]["IoU"] for v in views for k in ("shelf", "box")])

