"""Run a Python script in a subprocess and signal it once it says it is ready (tests only)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

SRC = str(Path(__file__).resolve().parents[2] / "src")


def run_and_signal(script: str, args: list[str], sig: int, ready: str) -> tuple[int, str]:
    """Start ``python -c script args`` with stemmap's source on the path, wait for the line
    ``ready`` on its stdout, send ``sig``: (exit code, stderr). SIGINT is left at its default
    in the child, as a shell does (Python then raises KeyboardInterrupt)."""
    return signal_when_ready([sys.executable, "-c", script, *args], sig, ready)


def signal_when_ready(
    cmd: list[str], sig: int, ready: str, extra_path: tuple[str, ...] = ()
) -> tuple[int, str]:
    """:func:`run_and_signal` for any command ``cmd`` (e.g. ``python -m module``), with
    stemmap's source and ``extra_path`` on ``PYTHONPATH``."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([SRC, *extra_path]))
    with subprocess.Popen(
        cmd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    ) as p:
        assert p.stdout is not None and p.stdout.readline().strip() == ready
        p.send_signal(sig)
        _, err = p.communicate(timeout=60)
    return p.returncode, err
