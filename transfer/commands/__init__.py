"""`transfer` sub-commands. Shared argparse options for the training-based commands."""
from __future__ import annotations

import argparse

from racklay.cli import at_least, positive_float
from racklay.commands.train import image_size_arg


def add_model_args(p: argparse.ArgumentParser, from_checkpoint: bool = False) -> None:
    g = p.add_argument_group("model" + (" (default: the checkpoint's)" if from_checkpoint else ""))
    g.add_argument("--image-size", type=image_size_arg, help="network input: S (square) or HxW, multiples of 32")
    g.add_argument("--layout-size", type=int, help="layout grid size D the model predicts")
    g.add_argument("--R", type=int, help="shelves per image (layout channels); must match the data")
    if not from_checkpoint:
        g.add_argument("--decoder", choices=("light", "paper"), help="decoder: light (fast, default) or paper")
        g.add_argument("--disc", action=argparse.BooleanOptionalAction, default=None,
                       help="train with patch discriminators (the paper's '-disc' variant; TrainConfig's "
                            "default is on, --no-disc is ~25%% faster)")


def add_train_args(p: argparse.ArgumentParser, title: str = "training (defaults: racklay.train.TrainConfig's)",
                   helps: dict | None = None, single_run: bool = True) -> None:
    """The TrainConfig flags every transfer command shares. `helps` overrides a flag's help text
    (compare's apply to several runs); `single_run` adds --seed and --resume (compare has its own
    --seeds and resumes by itself)."""
    h = {"epochs": "training epochs (default: TrainConfig's)",
         "batch-size": "images per step (default: TrainConfig's)",
         "lr": "learning rate",
         "patience": "early stopping: epochs without validation improvement (0: off)",
         "workers": "DataLoader workers (0 is often fastest on 2 cores)",
         "max-minutes": "time budget for the run; stops cleanly and keeps the best",
         **(helps or {})}
    g = p.add_argument_group(title)
    g.add_argument("--epochs", type=at_least(1), help=h["epochs"])
    g.add_argument("--batch-size", type=at_least(1), help=h["batch-size"])
    g.add_argument("--lr", type=positive_float, help=h["lr"])
    g.add_argument("--patience", type=at_least(0), help=h["patience"])
    g.add_argument("--workers", type=at_least(0), help=h["workers"])
    g.add_argument("--max-minutes", type=positive_float, help=h["max-minutes"])
    if single_run:
        g.add_argument("--seed", type=int, default=0, help="seed for init, data order and augmentation (default 0)")
        g.add_argument("--resume", action="store_true", help="continue an interrupted run in --out (same settings)")
    add_set_arg(g)


def add_set_arg(g) -> None:
    g.add_argument("--set", dest="train_set", action="append", default=[], metavar="KEY=VALUE",
                   help="any other racklay.train.TrainConfig field, YAML value (repeatable): "
                        "--set amp=bf16 --set warmup_steps=20")


def parse_sets(items) -> dict:
    """['amp=bf16', 'warmup_steps=20'] -> {'amp': 'bf16', 'warmup_steps': 20} (checked against TrainConfig)."""
    import dataclasses

    import yaml

    from racklay.train import TrainConfig

    names = {f.name for f in dataclasses.fields(TrainConfig)}
    out = {}
    for item in items or []:
        key, eq, val = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        if key not in names:
            import difflib
            close = difflib.get_close_matches(key, sorted(names), n=1)
            raise ValueError(f"--set: TrainConfig has no field {key!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
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
