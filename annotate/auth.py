"""Logins for `annotate serve --auth-file FILE`: several users, salted scrypt password hashes,
throttled failed logins.

The login file has one line per user (blank lines and `#` comments are ignored)::

    ana:scrypt:16384:8:1:SALT_HEX:HASH_HEX

written by `annotate passwd FILE USER` (the password is read from the terminal or stdin, never
from the command line) with a fresh 16-byte salt per user. The server re-reads the file when it
changes, so a user added while it runs can log in at once.

Failed logins are throttled per user name: each failure waits a little longer before the answer
(0.25 s doubling up to 4 s, without blocking the server), and MAX_FAILS failures in a row lock
the name out for LOCKOUT_S seconds, during which even the right password is refused. Every
failure and lock-out is logged on stderr.
"""
from __future__ import annotations

import asyncio
import hashlib
import hmac
import os
import re
import secrets
import sys
import threading
import time
from collections import OrderedDict
from pathlib import Path

SCRYPT_N, SCRYPT_R, SCRYPT_P, SALT_BYTES, KEY_BYTES = 2**14, 8, 1, 16, 32
MIN_PASSWORD = 8
MAX_FAILS = 5          # failures in a row before a lock-out
LOCKOUT_S = 300.0      # how long a name stays locked out
_USER = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,63}$")


class AuthError(ValueError):
    """A login file or user name that cannot be used; the message names the file."""


def check_user_name(user: str, source: str = "user name") -> str:
    if not isinstance(user, str) or not _USER.match(user):
        raise AuthError(f"{source}: {user!r} is not a valid user name (letters, digits and . _ @ -, "
                        "up to 64 characters, starting with a letter or digit)")
    return user


def hash_password(password: str, salt: bytes | None = None) -> str:
    """'scrypt:N:r:p:SALT_HEX:HASH_HEX' for `password` with a fresh random salt."""
    salt = secrets.token_bytes(SALT_BYTES) if salt is None else salt
    key = hashlib.scrypt(password.encode("utf-8"), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P,
                         maxmem=2**26, dklen=KEY_BYTES)
    return f"scrypt:{SCRYPT_N}:{SCRYPT_R}:{SCRYPT_P}:{salt.hex()}:{key.hex()}"


def verify_password(password: str, stored: str) -> bool:
    kind, n, r, p, salt, key = stored.split(":")
    got = hashlib.scrypt(password.encode("utf-8"), salt=bytes.fromhex(salt), n=int(n), r=int(r), p=int(p),
                         maxmem=2**26, dklen=len(key) // 2)
    return hmac.compare_digest(got.hex(), key)


def read_users(path: str | os.PathLike) -> dict[str, str]:
    """user -> stored hash from a login file. AuthError naming the file and line if it is bad."""
    path = Path(path)
    if not path.is_file():
        raise AuthError(f"{path}: login file not found (create it with `annotate passwd {path} USER`)")
    users: dict[str, str] = {}
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        user, _, stored = line.partition(":")
        parts = stored.split(":")
        ok = len(parts) == 6 and parts[0] == "scrypt" and all(x.isdigit() for x in parts[1:4])
        try:
            ok = ok and len(bytes.fromhex(parts[4])) >= 8 and len(bytes.fromhex(parts[5])) >= 16
        except ValueError:
            ok = False
        if not ok:
            raise AuthError(f"{path}:{i}: not a login line (expected USER:scrypt:N:r:p:SALT:HASH, "
                            "as written by `annotate passwd`)")
        check_user_name(user, f"{path}:{i}")
        if user in users:
            raise AuthError(f"{path}:{i}: user {user!r} is listed twice")
        users[user] = stored
    return users


def set_password(path: str | os.PathLike, user: str, password: str | None) -> bool:
    """Add `user` to the login file (created if missing, readable by its owner only) or change
    their password; password None removes them. Returns True if the user existed before."""
    from racklay.atomic import atomic_write_text

    path = Path(path)
    check_user_name(user)
    users = read_users(path) if path.exists() else {}
    existed = user in users
    if password is None:
        if not existed:
            raise AuthError(f"{path}: no user {user!r}")
        del users[user]
    else:
        if len(password) < MIN_PASSWORD:
            raise AuthError(f"password for {user!r}: at least {MIN_PASSWORD} characters, please")
        users[user] = hash_password(password)
    text = "# annotate serve --auth-file: one USER:scrypt:N:r:p:SALT:HASH line per user (annotate passwd)\n"
    text += "".join(f"{u}:{h}\n" for u, h in users.items())
    atomic_write_text(path, text, mode=0o600)
    return existed


class Authenticator:
    """The login check gradio calls (`auth=Authenticator(path).check`, an async callable so the
    throttling waits never block the server)."""

    def __init__(self, path: str | os.PathLike, clock=time.monotonic, sleep=asyncio.sleep, log=None):
        self.path = Path(path)
        self.clock, self.sleep = clock, sleep
        self.log = log or (lambda msg: print(f"annotate: {msg}", file=sys.stderr, flush=True))
        self._users = read_users(self.path)
        if not self._users:
            raise AuthError(f"{self.path}: no users (add one with `annotate passwd {self.path} USER`)")
        self._stamp = self._file_stamp()
        # user -> (failures in a row, locked until, attempts being checked now)
        self._fails: OrderedDict[str, tuple[int, float, int]] = OrderedDict()
        self._lock = threading.Lock()

    def _file_stamp(self):
        st = self.path.stat()
        return st.st_mtime_ns, st.st_size, st.st_ino

    def users(self) -> dict[str, str]:
        """The login table, re-read when the file changed (a bad edit keeps the last good table)."""
        try:
            stamp = self._file_stamp()
            if stamp != self._stamp:
                self._users, self._stamp = read_users(self.path), stamp
        except (OSError, AuthError) as e:
            self.log(f"login file not re-read, keeping the previous users: {e}")
        return self._users

    def locked(self, user: str) -> float:
        """Seconds left of `user`'s lock-out (0 when not locked)."""
        with self._lock:
            until = self._fails.get(user, (0, 0.0, 0))[1]
        return max(0.0, until - self.clock())

    def _verify(self, user: str, password: str) -> bool:
        stored = self.users().get(user)
        if stored is None:
            hash_password(password, b"\0" * SALT_BYTES)   # same work as for a known name
            return False
        return verify_password(password, stored)

    async def check(self, username: str, password: str) -> bool:
        """True when the password is right and the name is not locked out. Atomic under
        concurrency: each attempt reserves its place among the MAX_FAILS a name may have before it
        is checked, so a burst of parallel attempts checks at most MAX_FAILS passwords; a lock-out,
        once set, is never cleared by an attempt that finishes later, and refuses even the right
        password that was being checked when it was set."""
        user = str(username)
        with self._lock:
            n, until, flying = self._fails.pop(user, (0, 0.0, 0))
            left = until - self.clock()
            full = n + flying >= MAX_FAILS
            self._fails[user] = (n, until, flying + (0 if left > 0 or full else 1))
            while len(self._fails) > 10000:                # bounded, whatever names are tried
                self._fails.popitem(last=False)
        if left > 0 or full:
            why = f"locked out for another {left:.0f} s" if left > 0 else f"{MAX_FAILS} attempts already under way"
            self.log(f"login refused for {user!r}: {why}")
            await self.sleep(1.0)
            return False
        ok, in_a_row, new_lock = False, 0, False
        try:
            ok = await asyncio.to_thread(self._verify, user, str(password))
        finally:
            with self._lock:
                n, until, flying = self._fails.pop(user, (0, 0.0, 1))
                locked = until > self.clock()          # set by another attempt while this one was checked
                if ok and not locked:
                    n = 0
                elif not ok:
                    n += 1
                    in_a_row = n
                    if n >= MAX_FAILS and not locked:
                        until, n, new_lock = self.clock() + LOCKOUT_S, 0, True
                self._fails[user] = (n, until, max(0, flying - 1))
        if ok and not locked:
            return True
        if new_lock:
            self.log(f"{MAX_FAILS} failed logins in a row for {user!r}: locked out for {LOCKOUT_S:.0f} s")
        elif locked:
            self.log(f"login refused for {user!r}: locked out while its password was checked")
        else:
            self.log(f"failed login for {user!r} ({n} in a row)")
        await self.sleep(1.0 if locked else min(0.25 * 2 ** (in_a_row - 1), 4.0))
        return False
