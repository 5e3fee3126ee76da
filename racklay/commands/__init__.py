"""One module per `racklay` sub-command; each defines `register(subparsers)`. racklay/cli.py
imports them by name (COMMANDS); they import nothing back from it: option types come from
racklay.config, the user-error type from here."""


class CLIError(Exception):
    """An error for the user: printed as one line, exit code 2."""


def add_progress_arg(p) -> None:
    """--no-progress, the same on every command that loops over images."""
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bar (there is none anyway when stderr is not a terminal, e.g. in a log file)")


def show_progress(args) -> bool:
    """A progress bar only where someone watches it: stderr is a terminal and --no-progress is not given."""
    import sys

    return sys.stderr.isatty() and not getattr(args, "no_progress", False)
