"""Pretrain / fine-tune / real-only training as thin layers over `racklay.train.train`.

Nothing here has a training loop: each function builds a `racklay.config.TrainConfig` with the
defaults that suit its step of the transfer workflow (paper §5.5) and calls `train(cfg,
transform=...)`. Real-data training (fine-tune and real-only) gets the paper's augmentation
(`transfer.augment.PaperAugment`, seeded from the run's seed) and carves its validation set from
the training split (`val_fraction`), as the real set only has train/test splits.
"""
from __future__ import annotations

import os
from pathlib import Path

from racklay.config import ARCH_FIELDS, TrainConfig, field_default, from_dict
from racklay.data import DataError, RackLayRoot

#: default learning-rate ratio of fine-tuning to training from scratch. 1: the from-scratch rate.
#: The paper's "lower LR" (0.2 until 2026-12-05) left the shipped model's fine-tune below the model it
#: started from on frames of a site it had photos of (3 seeds: box IoU 67.2 / 62.2 against 1.0's
#: 82.5 / 74.5) and did no better on a site it had none of (54.5 / 59.4 against 56.8 / 59.4;
#: docs/results/2026-12-05-forty-seventh-session.md)
FINETUNE_LR_RATIO = 1.0
#: default share of the real training split held out for validation / early stopping
REAL_VAL_FRACTION = 0.15


def train_config(**kw):
    """A `TrainConfig` from keyword arguments (None: TrainConfig's default); unknown names are a
    clear error (not ignored)."""
    return from_dict(TrainConfig, {k: v for k, v in kw.items() if v is not None}, "transfer", "training option")


def default_lr() -> float:
    return float(field_default(TrainConfig, "lr"))


def require_split(root: str | os.PathLike, split: str, what: str) -> RackLayRoot:
    """The dataset root with its split `split`; a clear error naming the splits found otherwise."""
    ds = RackLayRoot(root).require(f"{what} dataset")
    if not ds.split_ids(split):  # raises DataError naming the split files that exist
        raise DataError(f"{ds.split_path(split)}: {what} split {split!r} is empty")
    return ds


def dataset_shape(root: str | os.PathLike, split: str | None = None) -> tuple[int, int]:
    """(R, D) of a dataset's layouts, from its first sample (of `split` when given)."""
    import numpy as np

    ds = RackLayRoot(root)
    ids = ds.resolve(split) if split else ds.ids()
    views = ds.views()
    if not ids or not views:
        raise DataError(f"{ds.root}: no samples with layouts")
    p = ds.layout_path(views[0], ids[0])
    try:
        arr = np.load(p, mmap_mode="r", allow_pickle=False)
    except Exception as e:  # noqa: BLE001
        raise DataError(f"{p}: not a readable .npy array ({type(e).__name__})") from None
    if arr.ndim != 3:
        raise DataError(f"{p}: layouts must be (R, D, D), got shape {arr.shape}")
    return int(arr.shape[0]), int(arr.shape[-1])


def checkpoint_config(path: str | os.PathLike):
    """The model config stored in a checkpoint (clear error naming the file if unusable)."""
    from racklay.checkpoint import load_model

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: checkpoint not found")
    _, cfg, _ = load_model(p)
    return cfg


#: the loss settings a checkpoint records and a fine-tune keeps (`checkpoint_loss`; `transfer finetune`
#: flags that override them)
CHECKPOINT_LOSS = ("class_weights", "iou_weight", "gap_weight", "gap_loss_weight")


def checkpoint_loss(path: str | os.PathLike) -> dict:
    """The loss settings the checkpoint was trained with, from its `train_config` metadata:
    `class_weights` (tuple), `iou_weight`, `gap_weight` and `gap_loss_weight` (floats), each only when
    the file records it. A fine-tune keeps them: the release model was trained with boxes weighted 10, and fine-tuning it
    with another weighting moves its decisions (measured in docs/model-card.md, "Fine-tuning keeps
    the model's class weights")."""
    from racklay.checkpoint import load_checkpoint

    tc = load_checkpoint(path).meta.get("train_config") or {}
    own = {}
    if tc.get("class_weights"):
        own["class_weights"] = tuple(float(v) for v in tc["class_weights"])
    for k in CHECKPOINT_LOSS:
        if k != "class_weights" and tc.get(k) is not None:
            own[k] = float(tc[k])
    return own


def check_init_compatible(init: str | os.PathLike, real: str | os.PathLike, split: str = "train",
                          layout_size: int | None = None, R: int | None = None):
    """Before fine-tuning: the checkpoint's R (shelves) must match the real dataset's and a
    requested layout size D must match the checkpoint's, except for a `struct` checkpoint, whose
    structure is drawn at any size (the rule of `racklay.checkpoint.check_init`); the input size
    may differ: the network is convolutional. Returns the model config."""
    cfg = checkpoint_config(init)
    data_R, data_D = dataset_shape(real, split)
    if R is not None and R != cfg.R:
        raise ValueError(f"{init}: checkpoint predicts R={cfg.R} shelves, but R={R} was requested")
    if data_R != cfg.R:
        raise ValueError(f"{init}: checkpoint predicts R={cfg.R} shelves, but {real} has R={data_R} "
                         f"layout channels; fine-tune from a checkpoint trained with R={data_R}")
    if layout_size is not None and layout_size != cfg.layout_size and cfg.decoder != "struct":
        raise ValueError(f"{init}: checkpoint predicts {cfg.layout_size}x{cfg.layout_size} layouts (D) with the "
                         f"{cfg.decoder} decoder, but layout size {layout_size} was requested (only a struct "
                         f"checkpoint is fine-tuned at another size)")
    missing = [v for v in cfg.views if v not in RackLayRoot(real).views()]
    if missing:
        raise DataError(f"{real}: has no {'/'.join(missing)} layouts, which checkpoint {init} predicts")
    return cfg


def pretrain(synthetic, out, name: str = "pretrain", seed: int = 0, transform=None, **kw) -> Path:
    """Train on a synthetic RackLay root. Uses its `val` split when it has one, otherwise carves
    10% of `train`. Extra keyword arguments go to TrainConfig (epochs, lr, image_size, ...)."""
    from racklay.train import train

    ds = require_split(synthetic, kw.get("train_split") or "train", "synthetic")
    if "val_fraction" not in kw and "val_split" not in kw:
        if "val" in ds.splits():
            kw["val_split"] = "val"
        else:
            kw["val_fraction"] = 0.1
    cfg = train_config(data=str(synthetic), out=str(out), name=name, seed=seed, **kw)
    return Path(train(cfg, transform=transform))


def train_on_real(real, out, name: str, seed: int = 0, init=None, augment: bool = True,
                  val_fraction: float = REAL_VAL_FRACTION, lr: float | None = None, **kw) -> Path:
    """Fine-tune (`init` = a pretrain checkpoint) or train from scratch (`init=None`, the
    "real only" regime) on a real RackLay root, with the paper's augmentation and early
    stopping on a validation set carved from the training split."""
    from racklay.train import train

    from .augment import PaperAugment

    kw = {k: v for k, v in kw.items() if v is not None}  # None = default (the checkpoint's, below)
    train_split = kw.pop("train_split", None) or "train"
    require_split(real, train_split, "real")
    if init is not None:
        mcfg = check_init_compatible(init, real, train_split, layout_size=kw.get("layout_size"), R=kw.get("R"))
        for k in ARCH_FIELDS:   # the architecture comes from the checkpoint
            kw.setdefault(k, getattr(mcfg, k))
        for k, v in checkpoint_loss(init).items():   # the model's own loss, unless given
            kw.setdefault(k, v)
        if lr is None:
            lr = default_lr() * FINETUNE_LR_RATIO
    cfg = train_config(data=str(real), out=str(out), name=name, seed=seed, init=str(init) if init else None,
                       train_split=train_split, val_fraction=val_fraction, lr=lr, **kw)
    return Path(train(cfg, transform=PaperAugment(seed=seed) if augment else None))


def finetune(init, real, out, name: str = "finetune", seed: int = 0, **kw) -> Path:
    if init is None:
        raise ValueError("finetune needs --init CHECKPOINT (a pretrain checkpoint)")
    return train_on_real(real, out, name=name, seed=seed, init=init, **kw)


def best_weights(run_dir: str | os.PathLike) -> Path:
    """The checkpoint to evaluate from a training run folder."""
    run_dir = Path(run_dir)
    for n in ("best.safetensors", "last.safetensors"):
        if (run_dir / n).is_file():
            return run_dir / n
    raise FileNotFoundError(f"{run_dir}: no best.safetensors or last.safetensors (training did not finish?)")


def train_images(run_dir: str | os.PathLike) -> int | None:
    """How many training images a run used (its config.yaml through racklay.train.split_ids)."""
    from racklay.train import split_ids

    p = Path(run_dir) / "config.yaml"
    if not p.is_file():
        return None
    return len(split_ids(TrainConfig.from_yaml(p))[0])


def has_partial_run(out: str | os.PathLike, name: str) -> bool:
    """A killed run left OUT/NAME/last.safetensors: continue it with resume=True."""
    return (Path(out) / name / "last.safetensors").is_file()
