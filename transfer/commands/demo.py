"""transfer demo: the toolkit's main job end to end on a fresh machine (≈9 min on 2 CPU cores);
`--toy`: the seconds-long schematic demo of the data and metrics layer (`racklay.toy.toy_demo`)."""
from __future__ import annotations

from racklay.config import TrainConfig, add_flags, at_least


def add_demo_args(p) -> None:
    from ..demo import DemoConfig

    d = DemoConfig()
    p.add_argument("--out", default=d.out, help=f"output folder (default {d.out}); a second run reuses finished steps")
    p.add_argument("--seed", type=at_least(0), default=d.seed, help="seed for data, training and augmentation")
    p.add_argument("--weights", default=None, metavar="FILE",
                   help="model to start from (default: the shipped model, docs/model-card.md)")
    p.add_argument("--n-real", type=at_least(10), default=d.n_real, help=f"proxy-real images, >= 10 (default {d.n_real})")
    p.add_argument("--max-minutes", type=float, default=d.max_minutes,
                   help=f"time budget per training run (default {d.max_minutes:g})")
    add_flags(p, TrainConfig, ["amp"], default=None)
    p.add_argument("--photos", default=d.photos, metavar="DIR",
                   help="real photos to predict in step 1 (default: the 24 shipped with the package, "
                        "copies of photos of datasets/real-photos/)")
    p.add_argument("--real-photos", default=None, metavar="PROJECT",
                   help="Table 2 on labelled real photos: an annotate project whose SOURCES.tsv gives each "
                        "photo its split (`make demo` passes datasets/real-photos: split by site); without it, "
                        "on a rendered proxy-real set")
    p.add_argument("--quick", action="store_true", help="a smoke run of about a minute (not meaningful numbers)")
    p.add_argument("--toy", action="store_true",
                   help="instead: the schematic demo of the data/metrics layer (seconds, no training; "
                        "default --out outputs/demo)")
    p.add_argument("--n", type=at_least(1), default=24, help="--toy: number of schematic samples (default 24)")


DESCRIPTION = ("The toolkit's main job end to end, starting from the shipped model, with nothing "
               "downloaded: predict the demo photos (copies of photos of datasets/real-photos/; a figure per photo and "
               "a contact sheet), take the labelled real photos of --real-photos split by site (or, without it, "
               "render a small WareSynth 'proxy_real' set: a different look and camera effects, a stand-in for "
               "real photos, NOT real data), run a reduced `transfer "
               "compare` (synthetic only = the shipped model / real only / shipped model fine-tuned; 1 seed) and "
               "print the paper's Table 2 with the fine-tune's gain, plus the bar chart and learning curve. "
               "About 5-11 minutes on 2 CPU cores (measured: docs/model-card.md, Demo timing); each training "
               "run has a time budget. Prints where every output went. With --toy instead: build a small schematic "
               "dataset with the layout module, validate it with check-data, score a degraded copy of its "
               "layouts against the truth, and write a paper-style figure (seconds, no training).")


def register(sub) -> None:
    p = sub.add_parser("demo", help="the main job end to end: shipped model on real photos, sim -> real fine-tune "
                                    "(<10 min; --toy: seconds)",
                       description=DESCRIPTION)
    add_demo_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..demo import QUICK, TRAIN_OVERRIDES, DemoConfig, run_demo

    if args.toy:
        from racklay.toy import toy_demo

        return toy_demo("outputs/demo" if args.out == DemoConfig.out else args.out, n=args.n, seed=args.seed)
    kw = dict(out=args.out, seed=args.seed, weights=args.weights, n_real=args.n_real,
              max_minutes=args.max_minutes, photos=args.photos, real_photos=args.real_photos)
    if args.amp is not None:
        kw["train"] = {**TRAIN_OVERRIDES, "amp": args.amp}
    if args.quick:
        kw.update(QUICK)
    run_demo(DemoConfig(**kw))
    return 0
