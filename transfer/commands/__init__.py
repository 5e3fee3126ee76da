"""`transfer` sub-commands. Shared argparse options for the training-based commands."""
from __future__ import annotations

import argparse

from racklay.config import TrainConfig, add_flags, check_names


def add_model_args(p: argparse.ArgumentParser, from_checkpoint: bool = False) -> None:
    """Model flags (racklay train's, racklay/config.py); absent flags are None (the
    checkpoint's value with `from_checkpoint`, else TrainConfig's default)."""
    g = p.add_argument_group("model" + (" (default: the checkpoint's)" if from_checkpoint else ""))
    if from_checkpoint:
        add_flags(g, TrainConfig, ["image_size", "layout_size", "R"], default=None, helps={
            "image_size": "network input: S (square) or HxW, multiples of 32",
            "layout_size": "layout grid size D the model predicts",
            "R": "shelves per image (layout channels); must match the data"})
    else:
        add_flags(g, TrainConfig, ["image_size", "layout_size", "R", "decoder", "disc"], default=None)


def add_train_args(p: argparse.ArgumentParser, title: str = "training (defaults: racklay/config.py)",
                   helps: dict | None = None, single_run: bool = True) -> None:
    """The TrainConfig flags every transfer command shares, as `racklay train` defines them
    (racklay/config.py); absent flags are None (the workflow's or TrainConfig's default).
    `helps` replaces a flag's help text (compare's apply to several runs); `single_run` adds --seed
    and --resume (compare has its own --seeds and resumes by itself)."""
    g = p.add_argument_group(title)
    add_flags(g, TrainConfig, ["epochs", "batch_size", "lr", "patience", "workers", "max_minutes"], default=None,
              helps={"lr": "learning rate (default {default})",
                     "max_minutes": "time budget for the run; stops cleanly and keeps the best", **(helps or {})})
    if single_run:
        add_flags(g, TrainConfig, ["seed", "resume"], helps={"resume": "continue an interrupted run in --out (same settings)"})
        g.set_defaults(seed=0, resume=False)
    add_set_arg(g)


def add_set_arg(g) -> None:
    g.add_argument("--set", dest="train_set", action="append", default=[], metavar="KEY=VALUE",
                   help="any other racklay.config.TrainConfig field, YAML value (repeatable): "
                        "--set amp=bf16 --set warmup_steps=20")


def parse_sets(items) -> dict:
    """['amp=bf16', 'warmup_steps=20'] -> {'amp': 'bf16', 'warmup_steps': 20} (names checked against TrainConfig)."""
    import yaml

    out = {}
    for item in items or []:
        key, eq, val = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        check_names(TrainConfig, [key], "--set", "training option")
        try:
            out[key] = yaml.safe_load(val)
        except yaml.YAMLError:
            raise ValueError(f"--set {key}: not a YAML value: {val!r}") from None
    return out


def model_kwargs(args) -> dict:
    kw = dict(image_size=args.image_size, layout_size=args.layout_size, R=args.R)
    for k in ("decoder", "disc"):
        if getattr(args, k, None) is not None:
            kw[k] = getattr(args, k)
    return kw


def train_kwargs(args) -> dict:
    return dict(epochs=args.epochs, batch_size=args.batch_size, patience=args.patience, workers=args.workers,
                max_minutes=args.max_minutes, resume=True if args.resume else None, **parse_sets(args.train_set))


def split_out(out: str):
    """--out runs/NAME -> (runs, NAME): the run folder is exactly what the user named."""
    from pathlib import Path

    p = Path(out)
    return p.parent, p.name


def print_run(run) -> None:
    from pathlib import Path

    run = Path(run)
    print(f"run folder: {run}")
    for n in ("best.safetensors", "last.safetensors", "config.yaml", "metrics.csv"):
        if (run / n).exists():
            print(f"  {n:18s} {run / n}")
    for png in sorted(run.glob("*.png")):
        print(f"  {png.name:18s} {png}")
