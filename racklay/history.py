"""A run's history as people read it: `metrics.csv` (one row per epoch) and the curve figures
(`loss.png`, `metrics.png`), regenerated from the history the checkpoint keeps, so a resumed
run's files are complete."""
from __future__ import annotations

import csv
import io
from pathlib import Path

#: metrics.csv's columns that differ between two runs of the same recipe on the same data: the
#: clock and the threads the machine gave the run
MACHINE_COLUMNS = ("seconds", "elapsed_min", "val_seconds", "threads")


def history_row(epoch, step, lr, tr: dict, val: dict | None, seconds, elapsed, val_seconds=None,
                threads=None) -> dict:
    """One epoch's row of metrics.csv: step, learning rate, training losses, time (the epoch's,
    of it validation's, and the run's), the CPU threads that trained it (torch threads x
    processes, on a CPU), and the validation loss, score and per-view IoU when the epoch was
    validated."""
    row = {"epoch": epoch, "step": step, "lr": lr, **{f"train_{k}": v for k, v in tr.items()},
           "seconds": round(seconds, 1), "elapsed_min": round(elapsed / 60, 2)}
    if val_seconds is not None:
        row["val_seconds"] = round(val_seconds, 1)
    if threads is not None:
        row["threads"] = int(threads)
    if val is not None:
        row["val_loss"] = val["loss"]
        row["val_score"] = val["score"]
        for v, r in val["result"].items():
            for c in ("shelf", "box"):
                row[f"{v}_{c}_iou"] = r["dataset"][c]["IoU"]
            for k in ("rack", "box"):
                row[f"{v}_{k}_paper_miou"] = r["paper"][k]["mIoU"]
    return row


def write_history(run_dir: Path, history: list[dict]) -> None:
    """metrics.csv and the curve figures, regenerated from the history kept in the checkpoint."""
    from .atomic import atomic_write_text

    if not history:
        return
    keys: list[str] = []
    for row in history:
        keys += [k for k in row if k not in keys]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    for row in history:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    atomic_write_text(run_dir / "metrics.csv", buf.getvalue())
    try:
        plot_curves(run_dir, history)
    except Exception as e:  # noqa: BLE001 - a figure must never stop training
        print(f"warning: could not draw curves: {e}")


def read_history(path: str | Path) -> list[dict]:
    """A run's metrics.csv read back (PATH: the run folder or the file itself), one dict per epoch
    with its numbers as floats (`epoch` and `step` as ints; empty cells left out). A missing,
    empty or foreign file is a one-line error naming it."""
    path = Path(path)
    f = path / "metrics.csv" if path.is_dir() else path
    if not f.is_file():
        raise SystemExit(f"{f}: no such file (a `racklay train` run folder or its metrics.csv)")
    with open(f, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise SystemExit(f"{f}: no epochs recorded yet")
    if "epoch" not in rows[0] or "elapsed_min" not in rows[0]:
        raise SystemExit(f"{f}: not a run's metrics.csv (no epoch / elapsed_min column)")
    out = []
    for i, r in enumerate(rows, 2):
        try:
            out.append({k: (int(v) if k in ("epoch", "step") else float(v)) for k, v in r.items() if v not in ("", None)})
        except ValueError as e:
            raise SystemExit(f"{f}: line {i}: {e}") from None
    return out


def cpu_minutes(history: list[dict], threads: int | None = None) -> list[float | None]:
    """The run's CPU-minutes (wall time x threads x processes) at the end of each epoch, each
    epoch's wall time (from elapsed_min, which keeps an epoch's time from before a resume; its
    `seconds` do not) at the threads metrics.csv records for it, so a run resumed on another
    machine adds each part at its own count; an epoch recorded without them (before the column)
    at `threads` (the run config's, where set). None from the first epoch where neither says
    how many threads ran; GPU runs record none."""
    total, last, out = 0.0, 0.0, []
    for r in history:
        t = r.get("threads", threads)
        total = None if total is None or not t else total + (r["elapsed_min"] - last) * t
        last = r["elapsed_min"]
        out.append(total)
    return out


def run_cpu_minutes(path: str | Path) -> tuple[list[dict], list[float | None]]:
    """A run's metrics.csv rows (`read_history`) and its CPU-minutes at each epoch's end
    (`cpu_minutes`), with the threads of the run's config.yaml, where there is one, for epochs
    recorded without them. PATH is a run folder or a metrics.csv file (its config.yaml beside it)."""
    from .yamlfile import read_yaml_mapping

    path = Path(path)
    rows = read_history(path)
    cfg = (path if path.is_dir() else path.parent) / "config.yaml"
    threads = read_yaml_mapping(cfg, "run config").get("threads") if cfg.is_file() else None
    return rows, cpu_minutes(rows, threads)


def validation_series(history: list[dict]) -> dict[str, list[str]]:
    """The columns of metrics.csv that `metrics.png` draws, per panel: the dataset-level IoU per
    view and class with the validation score (what runs are compared by), and the paper-protocol
    mIoU per view and class (Table 1's cells). Training columns (`train_iou` is the soft-IoU loss
    term, not a validation IoU) are never among them."""
    keys: list[str] = []
    for row in history:
        keys += [k for k in row if k not in keys and not k.startswith("train_")]
    return {"dataset-level IoU": [k for k in keys if k.endswith("_iou") and not k.endswith("paper_miou")]
            + (["val_score"] if "val_score" in keys else []),
            "paper-protocol mIoU": [k for k in keys if k.endswith("_paper_miou")]}


def plot_curves(run_dir: Path, history: list[dict]) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    from .viz import save_figure

    ep = [r["epoch"] + 1 for r in history]
    fig, ax = plt.subplots(figsize=(6, 4))
    for k in ("train_loss", "train_ce", "val_loss"):
        ys = [r.get(k, float("nan")) for r in history]
        if any(y == y for y in ys):
            ax.plot(ep, ys, marker="o", label=k)
    ax.set_xlabel("epoch")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("loss")
    ax.set_title("losses")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, run_dir / "loss.png")

    panels = {title: keys for title, keys in validation_series(history).items() if keys}
    if not panels:
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4), squeeze=False)
    for ax, (title, keys) in zip(axes[0], panels.items()):
        for k in keys:
            ax.plot(ep, [r.get(k, float("nan")) for r in history], marker="o",
                    label=k.removesuffix("_paper_miou"), lw=2.5 if k == "val_score" else 1.2)
        ax.set_xlabel("epoch")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel(f"{title} (validation)")
        ax.set_ylim(0, 1)
        ax.set_title(title)
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, run_dir / "metrics.png")


__all__ = ["MACHINE_COLUMNS", "history_row", "write_history", "plot_curves", "validation_series",
           "read_history", "cpu_minutes", "run_cpu_minutes"]
