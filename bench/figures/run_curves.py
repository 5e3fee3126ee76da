"""Compare training runs by their validation curves: one line per run, one panel per metric, and
the same numbers printed as a markdown table, epoch by epoch.

    .venv/bin/python -m bench.figures.run_curves [NAME=]RUN [NAME=]RUN ... [--x epoch|cpu-minutes]
        [--metrics top_box_iou,top_shelf_iou,...] --out curves.png

RUN is a `racklay train` run folder (its metrics.csv; config.yaml for the threads of runs recorded
before metrics.csv kept them) or a metrics.csv file (e.g. one a GPU script copied back). An A/B
at equal epochs reads `--x epoch` (the default: the same learning rate at each point when the runs
share a schedule); one at equal CPU time reads `--x cpu-minutes` (wall minutes x threads x
processes: `racklay.history.run_cpu_minutes`). Metrics are metrics.csv's validation columns
(`racklay.history.validation_series`: dataset-level IoU per view and class, `val_score`, and the
paper-protocol mIoU), drawn x 100.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from racklay.history import run_cpu_minutes, validation_series

DEFAULT_METRICS = ("top_box_iou", "top_shelf_iou", "front_box_iou", "front_shelf_iou", "val_score")


def load_run(spec: str) -> tuple[str, list[dict], list]:
    """NAME=RUN or RUN -> (name, metrics.csv rows, CPU-minutes at each row's end)."""
    name, sep, path = spec.partition("=")
    if not sep:
        name, path = "", spec
    p = Path(path)
    rows, cpu = run_cpu_minutes(p)
    return name or (p.name if p.is_dir() else p.stem), rows, cpu


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", metavar="[NAME=]RUN", help="run folders or metrics.csv files")
    ap.add_argument("--x", choices=("epoch", "cpu-minutes"), default="epoch", help="the axis runs are compared along (default epoch)")
    ap.add_argument("--metrics", default=",".join(DEFAULT_METRICS),
                    help=f"comma-separated metrics.csv columns, one panel each (default {','.join(DEFAULT_METRICS)})")
    ap.add_argument("--out", default=None, help="figure to write (PNG); none: print only")
    args = ap.parse_args(argv)

    runs = [load_run(s) for s in args.runs]
    names = [n for n, _, _ in runs]
    if len(set(names)) < len(names):
        sys.exit(f"two runs are both named {max(set(names), key=names.count)!r}: name them NAME=RUN")
    metrics = [m for m in args.metrics.split(",") if m]
    known = {k for _, rows, _ in runs for keys in validation_series(rows).values() for k in keys}
    for m in metrics:
        if m not in known:
            sys.exit(f"--metrics: {m!r} is in no run's metrics.csv (they have: {', '.join(sorted(known)) or 'no validation'})")
    if args.x == "cpu-minutes":
        for name, _, cpu in runs:
            if cpu[-1] is None:
                sys.exit(f"{name}: its metrics.csv and config.yaml do not say how many threads trained it; "
                         "compare it --x epoch")

    # the table: one row per epoch, each metric's runs side by side, then each run's CPU-minutes
    print("| epoch | " + " | ".join(f"{m}: {n}" for m in metrics for n in names) + " | " + " | ".join(f"CPU-min: {n}" for n in names) + " |")
    print("|---" * (1 + len(names) * (len(metrics) + 1)) + "|")
    by_epoch = [{r["epoch"]: (r, c) for r, c in zip(rows, cpu)} for _, rows, cpu in runs]
    for e in sorted({e for run in by_epoch for e in run}):
        at = [run.get(e, ({}, None)) for run in by_epoch]
        cells = [f"{100 * r[m]:.1f}" if m in r else "" for m in metrics for r, _ in at]
        cells += ["" if c is None else f"{c:.0f}" for _, c in at]
        print(f"| {e + 1} | " + " | ".join(cells) + " |")

    if args.out:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.ticker import MaxNLocator

        from racklay.viz import save_figure

        cols = min(3, len(metrics))
        nrows = -(-len(metrics) // cols)
        fig, axes = plt.subplots(nrows, cols, figsize=(4.2 * cols, 3.3 * nrows), squeeze=False)
        for ax in axes.flat[len(metrics):]:
            ax.axis("off")
        for ax, m in zip(axes.flat, metrics):
            for name, rows, cpu in runs:
                pts = [(cpu[i] if args.x == "cpu-minutes" else r["epoch"] + 1, 100 * r[m])
                       for i, r in enumerate(rows) if m in r]
                if pts:
                    ax.plot(*zip(*pts), marker="o", ms=3, label=name)
            ax.set_title(m.removesuffix("_iou").replace("_paper_miou", " (paper mIoU)"), fontsize=10)
            ax.set_xlabel("CPU-minutes" if args.x == "cpu-minutes" else "epoch")
            if args.x == "epoch":
                ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.grid(alpha=0.3)
        for ax in axes[:, 0]:
            ax.set_ylabel("validation, x100")
        axes[0][0].legend(fontsize=8)
        fig.tight_layout()
        print(f"wrote {save_figure(fig, args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
