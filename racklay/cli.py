"""`racklay` command line. Each sub-command lives in its own module under racklay/commands/
and exposes `register(subparsers)`; add new ones to COMMANDS."""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from racklay.commands import CLIError

#: sub-command modules, in the order `racklay --help` lists them
COMMANDS = [                       # in workflow order: data, model, use, check
    "racklay.commands.synth",
    "racklay.commands.check_data",
    "racklay.commands.show",
    "racklay.commands.train",
    "racklay.commands.distill",
    "racklay.commands.eval",
    "racklay.commands.calibrate",
    "racklay.commands.predict",
    "racklay.commands.export",
    "racklay.commands.analyze",
    "racklay.commands.score",
]


def build_parser(prog: str = "racklay", description: str | None = None, commands=None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description=description or (
            "RackLay toolkit: estimate per-shelf top- and front-view layouts of warehouse racks "
            "from one photo; generate, check, score and show RackLay-format datasets.\n\n"
            "New here? `transfer demo` runs the whole pipeline on built-in data (about 6 min on 2 CPU "
            "cores). Every command has --help; the guides are in docs/ (README.md lists them). "
            "Transfer (pretrain / fine-tune / compare) is the `transfer` command; the labelling "
            "tool is `annotate`."),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in commands if commands is not None else COMMANDS:
        importlib.import_module(name).register(sub)
    if commands is None:
        # the demo moved to the `transfer` app (racklay never imports it); old scripts get told where
        moved = sub.add_parser("demo", help="moved: the demo is `transfer demo` (same options)", add_help=False,
                               prefix_chars="\0")   # every word after "demo" is just passed on
        moved.add_argument("rest", nargs="*")
        moved.set_defaults(func=_demo_moved)
    return parser


def _demo_moved(args) -> int:
    raise CLIError("the demo moved: run `transfer demo " + " ".join(args.rest) + "` (same options)")


def _version() -> str:
    from racklay import __version__
    return __version__


def os_error_line(e: OSError) -> str:
    """One line for an OSError: 'PATH: reason' when the error names a path, else its message."""
    if e.filename is None or not e.strerror:
        return str(e).splitlines()[0] if str(e) else type(e).__name__
    path = str(e.filename) + (f" -> {e.filename2}" if e.filename2 is not None else "")
    if isinstance(e, FileExistsError) and os.path.isfile(e.filename):
        return f"{path}: is a file, expected a folder"
    return f"{path}: {e.strerror.lower()}"


def run(parser: argparse.ArgumentParser, argv=None) -> int:
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    from racklay.runtime import exit_on_sigterm, tune_allocator

    tune_allocator()
    exit_on_sigterm()
    try:
        rc = args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except CLIError as e:
        print(f"{parser.prog}: error: {e}", file=sys.stderr)
        return 2
    except ValueError as e:
        # DataError, LayoutError and friends carry a one-line message naming the file
        print(f"{parser.prog}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        # a file we could not read or write (missing input, unwritable output, a folder where a
        # file was expected, a busy port ...): one line naming the path, no traceback
        print(f"{parser.prog}: error: {os_error_line(e)}", file=sys.stderr)
        return 2
    return int(rc or 0)


def main(argv=None) -> int:
    return run(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
