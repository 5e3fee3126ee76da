"""transfer demo: the toolkit's main job end to end on a fresh machine (≈9 min on 2 CPU cores)."""
from __future__ import annotations

from racklay.cli import at_least


def add_demo_args(p) -> None:
    from ..demo import DemoConfig

    d = DemoConfig()
    p.add_argument("--out", default=d.out, help=f"output folder (default {d.out}); a second run reuses finished steps")
    p.add_argument("--seed", type=int, default=d.seed, help="seed for data, training and augmentation")
    p.add_argument("--n-synthetic", type=at_least(10), default=d.n_synthetic, help=f"synthetic images, >= 10 (default {d.n_synthetic})")
    p.add_argument("--n-real", type=at_least(10), default=d.n_real, help=f"proxy-real images, >= 10 (default {d.n_real})")
    p.add_argument("--amp", choices=("none", "bf16"), default=d.amp,
                   help=f"training precision (default {d.amp}: CPU bf16 autocast, ≈2-3x faster on CPUs with AMX; none = fp32)")
    p.add_argument("--quick", action="store_true", help="a smoke run of well under a minute with tiny sizes (not meaningful numbers)")


DESCRIPTION = ("Synthetic -> real transfer end to end, with nothing downloaded: render a small WareSynth "
               "'complex' set and a small 'proxy_real' set (rendered with a different look and camera "
               "effects: a stand-in for real photos, NOT real data), run a reduced `transfer compare` "
               "(synthetic only / real only / synthetic -> real fine-tune; 1 seed; real fractions 25% and "
               "100%), print the paper's Table 2 for it, write the bar chart and learning curve, and run "
               "the fine-tuned model on the real photos in datasets/real-photos/ (no labels: their "
               "figures are shown, not scored). About 9 minutes on 2 free CPU cores (at most ~15); each training run "
               "has a time budget. Prints where every output went.")


def register(sub) -> None:
    p = sub.add_parser("demo", help="the main job end to end: synthetic -> real transfer (~9 min on 2 CPU cores)",
                       description=DESCRIPTION)
    add_demo_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..demo import QUICK, DemoConfig, run_demo

    kw = dict(out=args.out, seed=args.seed, n_synthetic=args.n_synthetic, n_real=args.n_real, amp=args.amp)
    if args.quick:
        kw.update(QUICK)
    run_demo(DemoConfig(**kw))
    return 0
