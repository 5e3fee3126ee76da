"""Tables and figures for `transfer compare`: Table 2 of the paper (mean ± std over seeds), the
honest dataset-level numbers beside it, a bar chart and a learning curve.

A *record* is the `result.json` of one evaluated run::

    {"regime": "synthetic" | "real" | "finetune", "fraction": float | None, "seed": int,
     "n_train": int | None, "metrics": <racklay.metrics.LayoutMetrics.result()>, ...}

Paper cells are the paper protocol (per image x shelf, empty-in-both = 1; "mAP" is pixel
precision). Its floor is high (an all-background prediction scores ~42/53 "mIoU" on a rack
set with 1-4 shelves), so the dataset-level IoU (confusion matrix over all pixels) is reported
next to it and is the number to judge progress by.
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from racklay.atomic import atomic_write_text

REGIMES = ("synthetic", "real", "finetune")
REGIME_LABELS = {"synthetic": "synthetic only", "real": "real only", "finetune": "synthetic → real fine-tune"}
VIEW_ORDER = ("top", "front")
PAPER_CLASSES = ("rack", "box")
#: paper-protocol cells of Table 2: (view, class, metric key in the metrics dict, column label)
PAPER_CELLS = [(v, c, m, f"{v} {c} {lab}") for v in VIEW_ORDER for c in PAPER_CLASSES
               for m, lab in (("mIoU", "mIoU"), ("pixel_precision", "prec."))]
#: dataset-level cells: (view, class name in metrics["dataset"], column label)
DATASET_CELLS = [(v, c, f"{v} {c} IoU") for v in VIEW_ORDER for c in ("shelf", "box")]
#: boxes as boxes (racklay.metrics, front view): (key in metrics["front"]["separation"]["shelves"],
#: column label); counts of shelves whose labels show separate loads, not x100
SEPARATION_CELLS = [("separated", "front shelves separated"), ("placed", "front shelves in place")]
#: every column of table.csv and runs.csv, in order
TABLE_LABELS = [lab for *_, lab in PAPER_CELLS] + [lab for *_, lab in DATASET_CELLS] + [lab for _, lab in SEPARATION_CELLS]
#: the paper's Table 2 (RackLay-D-disc, real test set), x100, same column order as PAPER_CELLS
PAPER_TABLE2 = {
    "synthetic": [78.19, 93.66, 77.30, 91.43, 85.47, 97.69, 81.01, 94.34],
    "real": [76.98, 93.80, 80.07, 92.20, 88.42, 97.79, 81.20, 93.04],
    "finetune": [95.05, 97.46, 92.47, 97.61, 95.15, 99.29, 94.73, 98.31],
}


def paper_value(metrics: dict, view: str, cls: str, key: str) -> float:
    try:
        return 100.0 * float(metrics[view]["paper"][cls][key])
    except (KeyError, TypeError):
        return float("nan")


def dataset_value(metrics: dict, view: str, cls: str, key: str = "IoU") -> float:
    try:
        return 100.0 * float(metrics[view]["dataset"][cls][key])
    except (KeyError, TypeError):
        return float("nan")


def separation_value(metrics: dict, key: str) -> float:
    """A front-view separation count of `racklay.metrics` (NaN for a result that predates it)."""
    try:
        return float(metrics["front"]["separation"]["shelves"][key])
    except (KeyError, TypeError):
        return float("nan")


def record_values(rec: dict) -> dict[str, float]:
    """Every table cell of one run: IoU cells x100, separation cells as counts."""
    m = rec["metrics"]
    out = {lab: paper_value(m, v, c, k) for v, c, k, lab in PAPER_CELLS}
    out.update({lab: dataset_value(m, v, c) for v, c, lab in DATASET_CELLS})
    out.update({lab: separation_value(m, k) for k, lab in SEPARATION_CELLS})
    return out


def _mean_std(xs: list[float]) -> tuple[float, float, int]:
    a = np.array([x for x in xs if not math.isnan(x)], dtype=np.float64)
    if not a.size:
        return float("nan"), float("nan"), 0
    return float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else 0.0, int(a.size)


def _same_fraction(rec: dict, fraction: float) -> bool:
    return rec["regime"] == "synthetic" or abs(float(rec.get("fraction") or 1.0) - fraction) < 1e-9


def summarize(records: list[dict], fraction: float = 1.0) -> dict[str, dict[str, tuple[float, float, int]]]:
    """{regime: {column label: (mean, std, n_seeds)}} at one real-data fraction."""
    out = {}
    for regime in REGIMES:
        recs = [r for r in records if r["regime"] == regime and _same_fraction(r, fraction)]
        if not recs:
            continue
        vals = [record_values(r) for r in recs]
        out[regime] = {k: _mean_std([v[k] for v in vals]) for k in vals[0]}
    return out


def _cell(ms: tuple[float, float, int]) -> str:
    mean, std, n = ms
    if n == 0:
        return "–"
    return f"{mean:.2f} ± {std:.2f}" if n > 1 else f"{mean:.2f}"


def _count_cell(ms: tuple[float, float, int]) -> str:
    mean, std, n = ms
    if n == 0:
        return "–"
    return f"{mean:.1f} ± {std:.1f}" if n > 1 else f"{mean:.0f}"


def targets(summary: dict) -> list[tuple[str, bool | None, str]]:
    """The issue's targets, evaluated on the means: (name, met?, detail). None = not measurable."""
    res = []
    fin, real, syn = summary.get("finetune"), summary.get("real"), summary.get("synthetic")
    if fin and real:
        d = fin["top box mIoU"][0] - real["top box mIoU"][0]
        dd = fin["top box IoU"][0] - real["top box IoU"][0]
        res.append(("fine-tuned beats real-only by >= 10 top-view box-mIoU points", d >= 10,
                    f"{d:+.2f} points (paper protocol; dataset-level top box IoU {dd:+.2f})"))
    else:
        res.append(("fine-tuned beats real-only by >= 10 top-view box-mIoU points", None, "regime missing"))
    if fin and syn:
        worse = [lab for _, _, _, lab in PAPER_CELLS if not fin[lab][0] > syn[lab][0]]
        res.append(("fine-tuned beats synthetic-only on every cell", not worse,
                    "all 8 paper cells higher" if not worse else "not higher on: " + ", ".join(worse)))
    else:
        res.append(("fine-tuned beats synthetic-only on every cell", None, "regime missing"))
    return res


def table_markdown(records: list[dict], fraction: float = 1.0, title: str = "") -> str:
    s = summarize(records, fraction)
    seeds = sorted({r["seed"] for r in records})
    test_n = next((r["metrics"][v]["images"] for r in records for v in VIEW_ORDER if v in r.get("metrics", {})), None)
    lines = []
    if title:
        lines += [f"### {title}", ""]
    lines.append(f"Real test split: {test_n} images; real training data: {fraction:.0%} of the training split; "
                 f"seeds: {', '.join(map(str, seeds))}; n = runs per row (mean ± sample std over them), ×100.")
    lines.append("")
    lines.append("Paper protocol (Table 2 layout; per image × shelf, a shelf empty in both counts 1; "
                 "'prec.' is the pixel precision the paper calls mAP):")
    lines.append("")
    labels = [lab for *_, lab in PAPER_CELLS]

    def name(r):  # runs per row: rows may differ when a compare was stopped early or shares a checkpoint
        return f"{REGIME_LABELS[r]} (n={max(v[2] for v in s[r].values())})"

    lines += _md_table(labels, [(name(r), [_cell(s[r][lab]) for lab in labels]) for r in REGIMES if r in s])
    lines.append("")
    lines.append("Dataset level (confusion matrix over all pixels of all shelves; an all-background "
                 "prediction scores 0 here — judge by these):")
    lines.append("")
    dlabels = [lab for *_, lab in DATASET_CELLS]
    lines += _md_table(dlabels, [(name(r), [_cell(s[r][lab]) for lab in dlabels]) for r in REGIMES if r in s])
    lines.append("")
    shown = next((separation_value(r["metrics"], "truth") for r in records
                  if not math.isnan(separation_value(r["metrics"], "truth"))), None)
    if shown is not None:
        slabels = [lab for _, lab in SEPARATION_CELLS]
        lines.append(f"Boxes as boxes (front view; the test labels show separate loads on {shown:.0f} shelves): "
                     "shelves the model separates too, and those with its gaps where the labels' are "
                     "(racklay.layout.separated_shelves; counts):")
        lines.append("")
        lines += _md_table(slabels, [(name(r), [_count_cell(s[r][lab]) for lab in slabels]) for r in REGIMES if r in s])
        lines.append("")
    lines.append("Paper's Table 2 (RackLay-D-disc, authors' 100 real test images, for reference):")
    lines.append("")
    lines += _md_table(labels, [(REGIME_LABELS[r] + " (paper)", [f"{x:.2f}" for x in PAPER_TABLE2[r]]) for r in REGIMES])
    lines.append("")
    lines.append("Targets (on the means above):")
    lines.append("")
    for name, ok, detail in targets(s):
        mark = "not measured" if ok is None else ("MET" if ok else "NOT MET")
        lines.append(f"- {name}: **{mark}** — {detail}")
    return "\n".join(lines) + "\n"


def _md_table(labels: list[str], rows: list[tuple[str, list[str]]]) -> list[str]:
    out = ["| training | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels)]
    return out + [f"| {name} | " + " | ".join(cells) + " |" for name, cells in rows]


def table_csv(records: list[dict], fraction: float = 1.0) -> str:
    s = summarize(records, fraction)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    labels = TABLE_LABELS
    w.writerow(["training", "seeds"] + [f"{lab} {k}" for lab in labels for k in ("mean", "std")])
    for regime in REGIMES:
        if regime in s:
            n = max(s[regime][lab][2] for lab in labels)
            w.writerow([regime, n] + [f"{x:.4f}" for lab in labels for x in s[regime][lab][:2]])
    return buf.getvalue()


def runs_csv(records: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    labels = TABLE_LABELS
    w.writerow(["regime", "fraction", "seed", "n_train", "train_seconds", "eval_seconds", "run"] + labels)
    for r in sorted(records, key=_sort_key):
        v = record_values(r)
        w.writerow([r["regime"], "" if r.get("fraction") is None else r["fraction"], r["seed"], r.get("n_train", ""),
                    f"{r.get('train_seconds', float('nan')):.1f}", f"{r.get('eval_seconds', float('nan')):.1f}",
                    r.get("run", "")] + [f"{v[lab]:.4f}" for lab in labels])
    return buf.getvalue()


def _sort_key(r: dict):
    return (REGIMES.index(r["regime"]), float(r.get("fraction") or 0), r["seed"])


def learning_curve_data(records: list[dict], column: str) -> dict[str, list[tuple[float, int | None, float, float, int]]]:
    """{regime: [(fraction, n_train, mean, std, n_seeds), ...]} for real / finetune."""
    out = {}
    for regime in ("real", "finetune"):
        fr = sorted({float(r["fraction"]) for r in records if r["regime"] == regime and r.get("fraction") is not None})
        pts = []
        for f in fr:
            recs = [r for r in records if r["regime"] == regime and abs(float(r["fraction"]) - f) < 1e-9]
            mean, std, n = _mean_std([record_values(r)[column] for r in recs])
            ns = [r.get("n_train") for r in recs if r.get("n_train") is not None]
            pts.append((f, int(round(np.mean(ns))) if ns else None, mean, std, n))
        if pts:
            out[regime] = pts
    return out


LC_COLUMNS = ("top box mIoU", "top box IoU", "front box mIoU", "front box IoU")


def learning_curve_markdown(records: list[dict]) -> str:
    lines = ["| real train fraction | images | " + " | ".join(f"{c} real only | {c} fine-tuned" for c in LC_COLUMNS) + " |",
             "|---|---|" + "---|---|" * len(LC_COLUMNS)]
    data = {c: learning_curve_data(records, c) for c in LC_COLUMNS}
    fr = sorted({p[0] for c in data.values() for pts in c.values() for p in pts})
    for f in fr:
        n = next((p[1] for c in data.values() for pts in c.values() for p in pts if p[0] == f and p[1]), None)
        cells = []
        for c in LC_COLUMNS:
            for regime in ("real", "finetune"):
                p = next((p for p in data[c].get(regime, []) if p[0] == f), None)
                cells.append(_cell(p[2:]) if p else "–")
        lines.append(f"| {f:g} | {n if n is not None else '?'} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def bar_chart(records: list[dict], out: str | Path, fraction: float = 1.0, title: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from racklay.viz import save_figure

    s = summarize(records, fraction)
    colours = {"synthetic": "#8c8c8c", "real": "#4c72b0", "finetune": "#dd8452"}
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2), gridspec_kw={"width_ratios": [len(PAPER_CELLS), len(DATASET_CELLS)]})
    for ax, cells, name in ((axes[0], [lab for *_, lab in PAPER_CELLS], "paper protocol (Table 2 cells)"),
                            (axes[1], [lab for *_, lab in DATASET_CELLS], "dataset-level IoU")):
        regimes = [r for r in REGIMES if r in s]
        width = 0.8 / max(len(regimes), 1)
        x = np.arange(len(cells))
        for i, regime in enumerate(regimes):
            means = [s[regime][c][0] for c in cells]
            stds = [s[regime][c][1] if s[regime][c][2] > 1 else 0 for c in cells]
            ax.bar(x + (i - (len(regimes) - 1) / 2) * width, means, width, yerr=stds, capsize=2,
                   color=colours[regime], label=REGIME_LABELS[regime])
        ax.set_xticks(x, [c.replace(" ", "\n", 2) for c in cells], fontsize=7)
        ax.set_ylim(0, 100)
        ax.set_ylabel("×100")
        ax.set_title(name, fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8, loc="lower left")
    n_seeds = len({r["seed"] for r in records})
    fig.suptitle(title or f"Real test split, {n_seeds} seed(s), mean ± std", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out)


def learning_curve_plot(records: list[dict], out: str | Path, title: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullLocator

    from racklay.viz import save_figure

    fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
    axes = axes.ravel()
    styles = {"real": ("#4c72b0", "o-", "real only"), "finetune": ("#dd8452", "s-", "synthetic → real fine-tune")}
    syn = [record_values(r) for r in records if r["regime"] == "synthetic"]
    for ax, col in zip(axes, LC_COLUMNS):
        ticks: dict[float, int | None] = {}
        for regime, pts in learning_curve_data(records, col).items():
            c, st, lab = styles[regime]
            xs = [p[0] for p in pts]
            ax.errorbar(xs, [p[2] for p in pts], yerr=[p[3] for p in pts], fmt=st, color=c, capsize=3, label=lab)
            for p in pts:
                ticks[p[0]] = ticks.get(p[0]) or p[1]
        if syn:
            m, sd, _ = _mean_std([v[col] for v in syn])
            ax.axhline(m, color="#8c8c8c", ls="--", label="synthetic only")
        ax.set_xscale("log")
        ax.xaxis.set_minor_locator(NullLocator())
        if ticks:
            fs = sorted(ticks)
            ax.set_xticks(fs, [f"{f:.0%}" + (f"\n{ticks[f]} img" if ticks[f] else "") for f in fs], fontsize=7)
            ax.set_xlim(min(fs) / 1.3, max(fs) * 1.3)
        ax.set_xlabel("share of the real training split used (images)", fontsize=8)
        ax.set_title(col + (" (paper protocol)" if "mIoU" in col else " (dataset level)"), fontsize=9)
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("×100")
    axes[2].set_ylabel("×100")
    axes[0].legend(fontsize=7)
    fig.suptitle(title or "Learning curve on the real test split (mean ± std over seeds)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out)


def write_report(out_dir: str | Path, records: list[dict], fraction: float = 1.0, title: str = "",
                 header: str = "") -> dict[str, Path]:
    """Write table.md, table.csv, runs.csv, learning_curve.csv/.md, chart.png and
    learning_curve.png into out_dir; return their paths."""
    out_dir = Path(out_dir)
    paths = {}
    md = table_markdown(records, fraction, title=title)
    lc = learning_curve_markdown(records)
    paths["table_md"] = atomic_write_text(out_dir / "table.md", (header + "\n" if header else "") + md +
                                          "\n### Learning curve\n\n" + lc)
    paths["table_csv"] = atomic_write_text(out_dir / "table.csv", table_csv(records, fraction))
    paths["runs_csv"] = atomic_write_text(out_dir / "runs.csv", runs_csv(records))
    paths["chart"] = bar_chart(records, out_dir / "chart.png", fraction)
    if any(r["regime"] in ("real", "finetune") for r in records):
        paths["learning_curve"] = learning_curve_plot(records, out_dir / "learning_curve.png")
    return paths
