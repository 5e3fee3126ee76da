"""`annotate` command line: the browser annotation tool for real rack photos.
Sub-commands are modules listed in COMMANDS, each with `register(subparsers)`."""
from __future__ import annotations

import sys

from racklay.cli import build_parser, run

COMMANDS: list[str] = [
    "annotate.commands.serve",
    "annotate.commands.export",
    "annotate.commands.textures",
    "annotate.commands.import_dataset",
    "annotate.commands.passwd",
]
DESCRIPTION = ("Annotate real rack photos into per-shelf top- and front-view layouts in the browser "
               "(gradio), and export them as a RackLay-format dataset.")


def main(argv=None) -> int:
    return run(build_parser("annotate", DESCRIPTION, COMMANDS), argv)


if __name__ == "__main__":
    sys.exit(main())
