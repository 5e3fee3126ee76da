"""annotate passwd FILE USER [--delete]"""
from __future__ import annotations

import sys


def register(sub) -> None:
    p = sub.add_parser(
        "passwd", help="add a user to a login file for `serve --auth-file`, or change or remove one",
        description="Add USER to the login file FILE (created if missing, readable by its owner only) or "
                    "change their password; --delete removes them. The password is asked for twice on "
                    "the terminal, or read as one line from stdin when stdin is not a terminal "
                    "(`printf '%s\\n' \"$PW\" | annotate passwd ...`); it is never a command-line "
                    "argument. The file stores a salted scrypt hash per user. A running server picks "
                    "up the change at the next login.")
    p.add_argument("file", help="login file (e.g. my_project.logins; keep it outside the project folder)")
    p.add_argument("user", help="user name (letters, digits and . _ @ -)")
    p.add_argument("--delete", action="store_true", help="remove USER from the file")
    p.set_defaults(func=run)


def read_password(user: str) -> str:
    from racklay.commands import CLIError

    if not sys.stdin.isatty():
        line = sys.stdin.readline()
        if not line:
            raise CLIError("no password on stdin")
        return line.rstrip("\r\n")
    import getpass

    pw = getpass.getpass(f"password for {user}: ")
    if getpass.getpass("again: ") != pw:
        raise CLIError("the two passwords differ; nothing changed")
    return pw


def run(args) -> int:
    from annotate.auth import check_user_name, set_password

    check_user_name(args.user)
    existed = set_password(args.file, args.user, None if args.delete else read_password(args.user))
    what = "removed" if args.delete else ("password changed for" if existed else "added")
    print(f"{what} {args.user} in {args.file}")
    return 0
