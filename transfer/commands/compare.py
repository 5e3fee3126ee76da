"""transfer compare: Table 2 of the paper (synthetic only / real only / fine-tuned) + learning curve."""
from __future__ import annotations

from racklay.config import at_least, positive_float

from . import add_model_args, add_train_args, parse_sets


def _floats(s: str) -> list[float]:
    try:
        return [float(x) for x in s.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--fractions must be comma-separated numbers, got {s!r}") from None


def register(sub) -> None:
    from ..workflow import FINETUNE_LR_RATIO, REAL_VAL_FRACTION

    p = sub.add_parser(
        "compare",
        help="synthetic-only vs real-only vs synthetic->real fine-tune (paper Table 2)",
        description="Run the three training regimes of the paper's Table 2 on the same real test split, "
                    "over several seeds: (1) pretrain on --synthetic and evaluate on the real test split; "
                    "(2) train the same architecture on the real training split only (random init, or "
                    "--imagenet-weights); (3) fine-tune each seed's pretrain checkpoint on the real "
                    "training split. (2) and (3) are repeated over --fractions of the real training split "
                    "(learning curve). Writes OUT/table.md and table.csv (Table 2 layout, mean +- std over "
                    "seeds, plus dataset-level IoU), runs.csv, chart.png and learning_curve.png. Each run "
                    "is a folder under OUT/runs/ with a result.json written last: run the same command "
                    "again to resume a killed compare without redoing finished runs.")
    p.add_argument("--synthetic", metavar="ROOT", help="synthetic RackLay-format root (pretrained here, once per seed)")
    p.add_argument("--pretrained", metavar="CHECKPOINT",
                   help="use this pretrain checkpoint for every seed instead of pretraining on --synthetic "
                        "per seed (cheaper; the synthetic-only row is then one model, scored once)")
    p.add_argument("--real", required=True, metavar="ROOT", help="real RackLay-format root with train and test splits")
    p.add_argument("--out", required=True, help="output folder (resumable)")
    p.add_argument("--seeds", type=at_least(1), default=3, help="number of seeds (0..N-1; default 3)")
    p.add_argument("--first-seed", type=at_least(0), default=0, help="first seed (default 0)")
    p.add_argument("--fractions", type=_floats, default=[0.1, 0.25, 0.5, 1.0],
                   help="fractions of the real training split for the learning curve (default 0.1,0.25,0.5,1.0); "
                        "Table 2 uses the largest")
    p.add_argument("--train-split", default="train", help="real training split (default train)")
    p.add_argument("--test-split", default="test", help="real test split (default test)")
    p.add_argument("--pretrain-epochs", type=at_least(1), help="epochs on synthetic data")
    p.add_argument("--pretrain-max-minutes", type=positive_float, help="time budget per pretrain run")
    p.add_argument("--finetune-lr", type=float,
                   help=f"fine-tune learning rate (default {FINETUNE_LR_RATIO:g}x the from-scratch one)")
    p.add_argument("--freeze-encoder-epochs", type=at_least(0), default=0, help="fine-tune: frozen-encoder epochs (default 0)")
    p.add_argument("--val-fraction", type=float, default=REAL_VAL_FRACTION,
                   help=f"share of the real training split held out for early stopping (default {REAL_VAL_FRACTION:g})")
    p.add_argument("--imagenet-weights", metavar="FILE",
                   help="local torchvision resnet18 weights for the encoder of from-scratch runs")
    p.add_argument("--no-augment", action="store_true", help="train on real data without the paper's augmentation")
    p.add_argument("--eval-batch-size", type=at_least(1), default=8, help="images per forward pass when scoring (default 8)")
    add_model_args(p)
    add_train_args(p, "training of every run (defaults: racklay/config.py)", single_run=False, helps={
        "epochs": "epochs of real-only and fine-tune runs",
        "lr": "learning rate of pretrain and real-only runs",
        "max_minutes": "time budget per real-only / fine-tune run"})
    p.set_defaults(func=run)


def run(args) -> int:
    from ..compare import CompareConfig, compare

    if args.seeds < 1:
        raise ValueError("--seeds must be >= 1")
    train = {k: getattr(args, k) for k in ("image_size", "layout_size", "R", "decoder", "disc", "batch_size",
                                           "patience", "workers") if getattr(args, k) is not None}
    cfg = CompareConfig(
        real=args.real, out=args.out, synthetic=args.synthetic, pretrained=args.pretrained,
        seeds=list(range(args.first_seed, args.first_seed + args.seeds)), fractions=args.fractions,
        real_train_split=args.train_split, real_test_split=args.test_split,
        pretrain_epochs=args.pretrain_epochs, epochs=args.epochs, lr=args.lr,
        finetune_lr=args.finetune_lr, freeze_encoder_epochs=args.freeze_encoder_epochs,
        imagenet_weights=args.imagenet_weights, val_fraction=args.val_fraction,
        augment=not args.no_augment, max_minutes=args.max_minutes, pretrain_max_minutes=args.pretrain_max_minutes,
        eval_batch_size=args.eval_batch_size, train={**train, **parse_sets(args.train_set)})
    res = compare(cfg)
    print()
    print((res["paths"]["table_md"]).read_text())
    print("outputs:")
    for k, v in res["paths"].items():
        print(f"  {k:15s} {v}")
    print(f"  {'runs':15s} {cfg.out}/runs/seed*/<regime>/ (result.json per run)")
    return 0
