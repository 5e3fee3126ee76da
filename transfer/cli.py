"""`transfer` command line: synthetic -> real transfer (pretrain, fine-tune, compare).
Sub-commands live in transfer/commands/ style modules listed in COMMANDS."""
from __future__ import annotations

import sys

from racklay.cli import build_parser, run

COMMANDS: list[str] = [
    "transfer.commands.pretrain",
    "transfer.commands.finetune",
    "transfer.commands.compare",
    "transfer.commands.demo",
]
DESCRIPTION = ("Sim-to-real transfer for RackLay: pretrain on synthetic data, fine-tune on a small real "
               "set with colour-jitter and flip augmentation, and compare synthetic / real / fine-tuned.")


def main(argv=None) -> int:
    return run(build_parser("transfer", DESCRIPTION, COMMANDS), argv)


if __name__ == "__main__":
    sys.exit(main())
