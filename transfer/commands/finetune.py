"""transfer finetune: fine-tune a pretrain checkpoint on a small real set."""
from __future__ import annotations

from racklay.config import TrainConfig, add_flags, at_least

from . import add_model_args, add_train_args, print_run, split_out, train_kwargs


def register(sub) -> None:
    from ..workflow import CHECKPOINT_LOSS, FINETUNE_LR_RATIO, REAL_VAL_FRACTION

    p = sub.add_parser(
        "finetune",
        help="fine-tune the shipped model (or a pretrain checkpoint) on real data (step 2)",
        description="Fine-tune a checkpoint (from `transfer pretrain`) on a real RackLay-format dataset "
                    "(the authors' real-world set, or `annotate export` output) with the paper's "
                    "augmentation: colour jitter (brightness/contrast/saturation in [0.8, 1.2], hue "
                    "+-0.1, p=0.5) and horizontal flip (p=0.5) applied to the image and every layout "
                    "channel (albumentations). Learning rate "
                    f"{FINETUNE_LR_RATIO:g}x TrainConfig's unless --lr, optional encoder freezing for the first "
                    "epochs, early stopping on a validation set carved from the training split. The "
                    "architecture (R, layout size, input size, decoder, discriminators) comes from the checkpoint; a "
                    "checkpoint whose R or layout size does not fit is refused with a clear error (a struct "
                    "checkpoint is fine-tuned at any --layout-size).")
    p.add_argument("--init", default=None, metavar="CHECKPOINT",
                   help="checkpoint to start from (default: the shipped model, docs/model-card.md; or a "
                        "`transfer pretrain` checkpoint)")
    p.add_argument("--real", required=True, metavar="ROOT", help="real RackLay-format dataset root with split files")
    p.add_argument("--out", default="runs/finetune", help="run folder (default runs/finetune)")
    p.add_argument("--train-split", default="train", help="split to fine-tune on (default train)")
    p.add_argument("--fraction", type=float, default=None,
                   help="use only this fraction of the training split (reproducible by seed)")
    p.add_argument("--val-fraction", type=float, default=REAL_VAL_FRACTION,
                   help=f"share of the training split held out for early stopping (default {REAL_VAL_FRACTION:g})")
    p.add_argument("--freeze-encoder-epochs", type=at_least(0), default=0,
                   help="keep the encoder frozen for the first N epochs (default 0)")
    p.add_argument("--no-augment", action="store_true", help="disable the paper's augmentation")
    add_model_args(p, from_checkpoint=True)
    add_train_args(p, helps={"lr": f"learning rate (default {FINETUNE_LR_RATIO:g} x TrainConfig's {{default}})"})
    add_flags(p.add_argument_group("loss"), TrainConfig, list(CHECKPOINT_LOSS), default=None, helps={
        "class_weights": "cross-entropy weights background,shelf,box (default: the ones the checkpoint was "
                         "trained with, from its metadata; else TrainConfig's {default})",
        "iou_weight": "weight of the soft-IoU loss (default: the checkpoint's, from its metadata; else "
                      "TrainConfig's {default})",
        "gap_weight": "struct models: weight of the box loss at gaps between boxes (default: the checkpoint's, "
                      "from its metadata; else TrainConfig's {default})",
        "gap_loss_weight": "struct models with a gap output: weight of its own loss (default: the checkpoint's, "
                           "from its metadata; else TrainConfig's {default})"})
    add_flags(p.add_argument_group("synthetic replay"), TrainConfig, ["replay", "replay_ratio"], default=None, helps={
        "replay": "synthetic RackLay root (e.g. the release set, or `racklay synth` output) whose train split "
                  "is mixed into every epoch, so a fine-tune on a few dozen photos does not forget the "
                  "renders (docs/transfer.md); repeat the flag to pool several sets"})
    p.set_defaults(func=run)


def run(args) -> int:
    from racklay.data import RackLayRoot

    from ..workflow import CHECKPOINT_LOSS, finetune, require_split

    # the data first: a wrong path is one line at once, not after the model has loaded
    require_split(args.real, args.train_split, "real")
    for path in args.replay or ():
        RackLayRoot(path).require("replay dataset")
    if args.fraction is not None and not 0 < args.fraction <= 1:
        raise ValueError(f"--fraction must be in (0, 1], got {args.fraction}")
    from racklay.release import weights_for_cli

    out, name = split_out(args.out)
    kw = train_kwargs(args)
    for k in (*CHECKPOINT_LOSS, "replay", "replay_ratio"):   # absent: the checkpoint's / TrainConfig's
        if getattr(args, k) is not None:
            kw[k] = getattr(args, k)
    run_dir = finetune(weights_for_cli(args.init, flag="--init"), args.real, out, name=name, seed=args.seed, lr=args.lr,
                       train_split=args.train_split, train_fraction=args.fraction,
                       val_fraction=args.val_fraction, freeze_encoder_epochs=args.freeze_encoder_epochs,
                       augment=not args.no_augment, image_size=args.image_size, layout_size=args.layout_size,
                       R=args.R, **kw)
    print_run(run_dir)
    return 0
