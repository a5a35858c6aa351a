"""Ctrl-C or SIGTERM while ``stemmap`` is still importing its commands (~1 s on a loaded
machine) ends it with one ``error:`` line and exit code 130 / 143, like a signal during the
run; before, Python printed the traceback of whatever import was running (the commands were
imported when ``stemmap.cli`` itself was, before ``main`` could install any handling)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

# A real signal, delivered while the entry point imports typer: an import hook announces the
# import on stdout and then waits, so the test knows the process is inside it.
_STALLED_IMPORT = """
import sys, time

class Stall:
    def find_spec(self, name, path=None, target=None):
        if name == "typer":
            print("importing", flush=True)
            time.sleep(60)
        return None

sys.meta_path.insert(0, Stall())
sys.argv = ["stemmap", "--help"]
from stemmap.cli import main  # what the console script does
main()
"""


@pytest.mark.parametrize(
    ("sig", "code", "line"),
    [
        (signal.SIGINT, 130, "error: interrupted (Ctrl-C) while starting; nothing was read"),
        (signal.SIGTERM, 143, "error: terminated (SIGTERM) while starting; nothing was read"),
    ],
)
def test_signal_during_imports_is_one_error_line(sig: int, code: int, line: str) -> None:
    from _signals import run_and_signal

    returncode, err = run_and_signal(_STALLED_IMPORT, [], sig, "importing")
    assert returncode == code, err
    assert "Traceback" not in err and line in err
    assert err.strip().count("\n") == 0  # one line


def test_importing_the_entry_point_loads_no_command() -> None:
    # the window a signal could still hit without handling: importing stemmap.cli itself
    script = (
        "import sys; from stemmap.cli import main; "
        "print(sorted(m for m in ('numpy', 'typer', 'rich', 'stemmap.types') if m in sys.modules))"
    )
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2] / "src"))
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]"


def test_the_app_is_still_importable() -> None:
    from stemmap.cli import app

    assert app.info.name == "stemmap"
