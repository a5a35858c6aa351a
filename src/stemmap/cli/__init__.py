"""The ``stemmap`` command-line interface (typer).

This module is the console-script entry point and is kept light on purpose: the commands
(:mod:`stemmap.cli._app`, ~0.9 s of imports: typer, rich, numpy, every command module) are
imported by :func:`main` only after it has installed its signal handling, so a Ctrl-C or a
SIGTERM that arrives while the program is still starting ends it with one ``error:`` line
and exit code 130 / 143, like one that arrives during the run -- not with a traceback of the
import that happened to be running. ``stemmap.cli.app`` still gives the typer app (loaded on
first use, PEP 562).
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import typer

    app: typer.Typer

__all__ = ["app", "main"]


def __getattr__(name: str) -> Any:
    if name == "app":
        from stemmap.cli._app import app

        return app
    raise AttributeError(f"module 'stemmap.cli' has no attribute {name!r}")


class _Terminated(SystemExit):
    """SIGTERM as an exception, so every ``with`` unwinds: run_products discards its staging
    folders (a job scheduler, ``timeout`` or ``docker stop`` end a run with SIGTERM; by default
    Python dies at once and left a hidden ``.stemmap-stage-*`` folder, like SIGKILL)."""


def _on_sigterm(signum: int, frame: Any) -> None:
    import signal

    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the cleanup
    raise _Terminated(128 + signum)


def _starting_error(message: str) -> None:
    """``error: ...`` on stderr without rich (which may be what was being imported)."""
    sys.stderr.write(f"error: {message}\n")
    sys.stderr.flush()


def main() -> None:
    """Console-script entry point (``stemmap``, ``python -m stemmap``).

    SIGTERM ends the run like Ctrl-C: products are discarded, exit code 143. Either signal
    while the commands are still being imported ends the program with one ``error:`` line
    (nothing has been read or written yet), exit code 130 (Ctrl-C) or 143 (SIGTERM).
    """
    import signal
    import threading

    if (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    ):
        signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        from stemmap.cli._app import app as typer_app
    except KeyboardInterrupt:
        _starting_error("interrupted (Ctrl-C) while starting; nothing was read or written.")
        # os._exit, not sys.exit: CPython may have flagged this interrupt as unhandled on its
        # way through C code, and under ``python -m`` that flag turns any exit status into
        # death by SIGINT (exit -2) after finalization. Nothing was opened or written yet, so
        # there is nothing for finalization to do (tests/cli/test_interrupt_while_starting.py).
        import os

        sys.stdout.flush()
        os._exit(130)
    except _Terminated:
        _starting_error("terminated (SIGTERM) while starting; nothing was read or written.")
        raise
    try:
        typer_app()
    except _Terminated:
        from stemmap.cli._common import print_error

        print_error("terminated (SIGTERM); the products of this run were not written.")
        raise
