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


def _writable_parent(path, what: str) -> None:
    """The nearest existing folder above `path` must be a folder this process can write into."""
    import os
    from pathlib import Path

    p = Path(path).absolute().parent
    while not p.exists():
        p = p.parent
    if not p.is_dir():
        raise CLIError(f"{path}: cannot write the {what} there ({p} is a file)")
    if not os.access(p, os.W_OK | os.X_OK):
        raise CLIError(f"{path}: cannot write the {what} there ({p} is not writable)")


def check_out_folder(path, what: str = "output folder") -> None:
    """Refuse an output folder that cannot be written, before any work is done: it is an existing
    file, or the folder it would be made in is missing-and-unmakeable or read-only."""
    import os
    from pathlib import Path

    p = Path(path)
    if p.is_dir():
        if not os.access(p, os.W_OK | os.X_OK):
            raise CLIError(f"{path}: the {what} is not writable")
    elif p.exists():
        raise CLIError(f"{path}: is a file, expected a folder ({what})")
    else:
        _writable_parent(p, what)


def check_out_file(path, what: str = "output file") -> None:
    """Refuse an output file that cannot be written, before any work is done: it is an existing
    folder, or the folder it would be written in is read-only or a file."""
    from pathlib import Path

    if path is None:
        return
    if Path(path).is_dir():
        raise CLIError(f"{path}: is a folder, expected a file ({what})")
    _writable_parent(path, what)
