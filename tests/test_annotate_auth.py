"""annotate serve --auth-file: several users with salted scrypt hashes written by `annotate
passwd` (password never on the command line), throttled failed logins with a lock-out, and the
old `--auth USER:PASSWORD` refused with a pointer to the new way."""
from __future__ import annotations

import asyncio
import io
import stat
import sys

import pytest

from annotate import auth as A
from annotate.cli import main as annotate_main


def _passwd(monkeypatch, capsys, *args, stdin="correct horse\n"):
    monkeypatch.setattr(sys, "stdin", io.StringIO(stdin))
    rc = annotate_main(["passwd", *args])
    out, err = capsys.readouterr()
    return rc, out, err


def test_passwd_writes_salted_hashes_readable_by_owner_only(tmp_path, monkeypatch, capsys):
    f = tmp_path / "logins"
    assert _passwd(monkeypatch, capsys, str(f), "ana")[:2] == (0, f"added ana in {f}\n")
    assert _passwd(monkeypatch, capsys, str(f), "ben")[0] == 0           # the same password
    text = f.read_text()
    assert "correct horse" not in text and stat.S_IMODE(f.stat().st_mode) == 0o600
    users = A.read_users(f)
    assert sorted(users) == ["ana", "ben"] and users["ana"] != users["ben"]   # one salt each
    assert A.verify_password("correct horse", users["ana"]) and not A.verify_password("correct horsf", users["ana"])
    assert _passwd(monkeypatch, capsys, str(f), "ana", stdin="battery staple\n")[1] == f"password changed for ana in {f}\n"
    assert A.verify_password("battery staple", A.read_users(f)["ana"])
    rc, _, err = _passwd(monkeypatch, capsys, str(f), "cy", stdin="short\n")
    assert rc == 2 and "at least 8 characters" in err and "cy" not in A.read_users(f)
    rc, _, err = _passwd(monkeypatch, capsys, str(f), "bad:name")
    assert rc == 2 and "not a valid user name" in err
    assert _passwd(monkeypatch, capsys, str(f), "ben", "--delete")[1] == f"removed ben in {f}\n"
    assert sorted(A.read_users(f)) == ["ana"]
    f.write_text(f.read_text() + "eve:plaintext-password\n")
    with pytest.raises(A.AuthError, match=r"logins:3: not a login line"):
        A.read_users(f)


def test_failed_logins_are_slowed_then_locked_out(tmp_path):
    f = tmp_path / "logins"
    A.set_password(f, "ana", "correct horse")
    A.set_password(f, "ben", "battery staple")
    now, waits, logged = [1000.0], [], []

    async def sleep(s):
        waits.append(s)

    auth = A.Authenticator(f, clock=lambda: now[0], sleep=sleep, log=logged.append)
    check = lambda u, p: asyncio.run(auth.check(u, p))
    assert check("ana", "correct horse") and check("ben", "battery staple") and waits == []
    results = [check("ana", f"guess {k}") for k in range(10)]
    assert results == [False] * 10
    assert waits[:5] == [0.25, 0.5, 1.0, 2.0, 4.0] and all(w >= 1.0 for w in waits[5:])
    assert "5 failed logins in a row for 'ana': locked out for 300 s" in logged
    assert not check("ana", "correct horse")          # locked: even the right password
    assert check("ben", "battery staple")             # other users are not affected
    now[0] += A.LOCKOUT_S + 1
    assert check("ana", "correct horse")
    # a user added while the server runs can log in at once; an unknown name never can
    A.set_password(f, "cy", "cy's password")
    assert check("cy", "cy's password") and not check("nobody", "cy's password")


def test_parallel_logins_cannot_bypass_the_lock_out(tmp_path):
    """40 simultaneous attempts for one name (the right password is number 21): at most MAX_FAILS
    passwords are checked, the right one is refused once the name is locked, and the lock-out stays
    set when the slower attempts finish (they used to clear it)."""
    import threading
    import time

    f = tmp_path / "logins"
    A.set_password(f, "ana", "correct horse")
    now, checked, lock = [1000.0], [], threading.Lock()

    async def no_wait(s):
        pass

    auth = A.Authenticator(f, clock=lambda: now[0], sleep=no_wait, log=lambda m: None)
    real = auth._verify

    def slow_verify(user, password):
        with lock:
            checked.append(password)
        time.sleep(0.05)                  # a scrypt check takes time: the attempts overlap
        return real(user, password)

    auth._verify = slow_verify

    async def burst():
        return await asyncio.gather(*(auth.check("ana", "correct horse" if k == 20 else f"guess {k}")
                                      for k in range(40)))

    results = asyncio.run(burst())
    assert len(checked) == A.MAX_FAILS and "correct horse" not in checked
    assert not any(results)
    assert auth.locked("ana") == A.LOCKOUT_S
    assert not asyncio.run(auth.check("ana", "correct horse"))      # still locked after the burst
    now[0] += A.LOCKOUT_S + 1
    assert asyncio.run(auth.check("ana", "correct horse"))


def test_auth_with_password_on_command_line_refused(tmp_path, capsys):
    rc = annotate_main(["serve", str(tmp_path / "proj"), "--auth", "ana:secret"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--auth-file" in err and "annotate passwd" in err
    assert not (tmp_path / "proj").exists()
    rc = annotate_main(["serve", str(tmp_path / "proj"), "--auth-file", str(tmp_path / "none")])
    assert rc == 2 and "none: login file not found" in capsys.readouterr().err


def test_saves_record_the_logged_in_user(tmp_path):
    """With several users, each session's saves carry its own login (kept across image changes)."""
    import numpy as np

    from annotate.editor import Tool
    from annotate.store import Project
    from racklay.atomic import encode_png

    for n in ("a.png", "b.png"):
        (tmp_path / n).write_bytes(encode_png(np.zeros((480, 640, 3), np.uint8)))
    proj = Project(tmp_path)
    tool = Tool(proj)
    ana, ben = tool.open("a.png", "ana"), tool.open("a.png", "ben")
    tool.click(ana, 100, 100)
    assert proj.load("a.png")["updated_by"] == "ana"
    ben = tool.step(ben, +1)                     # b.png
    tool.click(ben, 50, 60)
    assert proj.load("b.png")["updated_by"] == "ben"


def test_the_page_served_before_login_names_no_photo(tmp_path):
    """gradio serves its config and API description with the login page: the photo list is filled
    only when a (logged-in) session loads, so no file name is in them."""
    import json

    import numpy as np

    from annotate.app import build_app
    from annotate.store import Project
    from racklay.atomic import encode_png

    (tmp_path / "confidential_customer_site.png").write_bytes(encode_png(np.zeros((32, 48, 3), np.uint8)))
    demo = build_app(Project(tmp_path))
    for served in (demo.get_config_file(), demo.get_api_info()):
        assert "confidential_customer_site" not in json.dumps(served, default=str)
