"""One module per `racklay` sub-command; each defines `register(subparsers)`. racklay/cli.py
imports them by name (COMMANDS); they import nothing back from it: option types come from
racklay.config, the user-error type from here."""


class CLIError(Exception):
    """An error for the user: printed as one line, exit code 2."""
