"""transfer pretrain: train on a synthetic RackLay root (a thin layer over racklay.train)."""
from __future__ import annotations

from . import add_model_args, add_train_args, model_kwargs, print_run, split_out, train_kwargs


def register(sub) -> None:
    p = sub.add_parser(
        "pretrain",
        help="train on synthetic data (step 1 of sim-to-real transfer)",
        description="Train RackLay on a synthetic RackLay-format dataset (e.g. from `racklay synth "
                    "--recipe complex`). Uses the dataset's val split when it has one, otherwise carves "
                    "10% of train. This is racklay.train.train with the transfer defaults; the "
                    "checkpoint it writes (RUN/best.safetensors) is what `transfer finetune --init` takes.")
    p.add_argument("--synthetic", required=True, metavar="ROOT", help="synthetic RackLay-format dataset root")
    p.add_argument("--out", default="runs/pretrain", help="run folder (default runs/pretrain)")
    p.add_argument("--imagenet-weights", metavar="FILE",
                   help="local torchvision resnet18 weights to initialise the encoder (nothing is downloaded)")
    add_model_args(p)
    add_train_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..workflow import pretrain

    out, name = split_out(args.out)
    kw = {**model_kwargs(args), **train_kwargs(args)}
    run_dir = pretrain(args.synthetic, out, name=name, seed=args.seed, lr=args.lr,
                       imagenet_weights=args.imagenet_weights, **kw)
    print_run(run_dir)
    return 0
