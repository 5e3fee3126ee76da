"""Process-wide runtime settings (racklay.runtime): every command line tunes glibc's allocator
once, unless the user opted out or set glibc's own variables."""
from __future__ import annotations

import argparse

import pytest

import racklay.runtime as rt
from racklay.cli import run


@pytest.fixture
def fresh(monkeypatch):
    """tune_allocator() as if this process had not called it yet, with no glibc variables set."""
    monkeypatch.setattr(rt, "_applied", None)
    for var in (*rt.USER_VARS, rt.OPT_OUT):
        monkeypatch.delenv(var, raising=False)
    return rt


def test_tunes_glibc_once(fresh):
    if not fresh.is_glibc():
        pytest.skip("glibc only")
    assert fresh.tune_allocator() == "tuned"
    assert fresh.tune_allocator() == "tuned"        # a second call does nothing new


@pytest.mark.parametrize("var, value, outcome", [
    ("RACKLAY_NO_MALLOPT", "1", "opted out"),
    ("MALLOC_MMAP_THRESHOLD_", "4294967296", "user settings"),
    ("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=0", "user settings"),
])
def test_user_choices_win(fresh, monkeypatch, var, value, outcome):
    monkeypatch.setenv(var, value)
    assert fresh.tune_allocator() == outcome


def test_every_command_line_tunes_before_running(monkeypatch):
    calls = []
    monkeypatch.setattr(rt, "tune_allocator", lambda: calls.append("tuned") or "tuned")
    parser = argparse.ArgumentParser(prog="x")
    sub = parser.add_subparsers()
    sub.add_parser("go").set_defaults(func=lambda args: calls.append("ran") or 0)
    assert run(parser, ["go"]) == 0
    assert calls == ["tuned", "ran"]


def test_a_command_stopped_by_sigterm_leaves_no_hidden_partial_output(tmp_path):
    """`kill`, docker stop or a scheduler's time limit during an export: the command exits 143 and
    its hidden staging folder is removed, as on an error or Ctrl-C (it used to stay behind)."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent(f"""
        import argparse, os, signal, sys, time
        from pathlib import Path
        from annotate.dataset import staged_folder
        from racklay.cli import run

        def export(args):
            with staged_folder(Path({str(tmp_path / "out")!r})) as tmp:
                (tmp / "half.npy").write_bytes(b"x" * 1000)
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(30)
            return 0

        parser = argparse.ArgumentParser(prog="x")
        parser.add_subparsers().add_parser("export").set_defaults(func=export)
        sys.exit(run(parser, ["export"]))
    """)
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert p.returncode == 143, p.stderr
    assert list(tmp_path.iterdir()) == []
