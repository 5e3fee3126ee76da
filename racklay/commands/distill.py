"""racklay distill --data RENDERS --photos PHOTOS --out student.safetensors [--teacher W] [--struct-width 32]"""
from __future__ import annotations

import argparse

from racklay.commands import add_progress_arg


def register(sub) -> None:
    from racklay.config import add_flags
    from racklay.distill import DistillConfig

    p = sub.add_parser(
        "distill", help="a faster struct model that does what a trained one does (narrower decoders)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Distil a struct model (default: the shipped one) into a student with narrower struct decoders\n"
            "(--struct-width, --struct-fuse-k, no 1/4 branch) on the teacher's own encoder, copied and frozen.\n"
            "The student learns the teacher's structures (presence, length, extent, placement, per-position\n"
            "box and gap logits, box sizes) on the images given, without labels: renders (--data) and photos\n"
            "(--photos, drawn --photo-share of the time, also colour-jittered), each also mirrored. The\n"
            "encoder's features and the teacher's structures are computed once and held in memory, so a\n"
            "step runs the decoders alone. Score the student with `racklay eval` beside its teacher before\n"
            "using it; its speed with bench/speed/release_speed.py --weights. docs/training.md."),
        epilog="example:\n"
               "  racklay distill --data datasets/mixed --photos exported-photos:train --minutes 45 \\\n"
               "      --struct-width 32 --struct-fuse-k 1 --out runs/fast.safetensors")
    add_flags(p, DistillConfig)
    add_progress_arg(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from racklay.commands import CLIError, check_out_file, show_progress
    from racklay.config import from_dict
    from racklay.distill import DistillConfig, distill

    given = {k: v for k, v in vars(args).items() if k not in ("func", "command", "no_progress")}
    try:
        cfg = from_dict(DistillConfig, given, "flags")
    except ValueError as e:
        raise CLIError(str(e)) from None
    check_out_file(cfg.out, "student checkpoint")
    try:
        distill(cfg, progress=show_progress(args))
    except (ValueError, FileNotFoundError) as e:
        raise CLIError(str(e)) from None
    return 0
