"""Helpers shared by CLI commands: error reporting and progress bars (rich, CLI only)."""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Iterator
from typing import Annotated, Any

import numpy as np
import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from stemmap.errors import StemmapError

__all__ = [
    "ProgressFlag",
    "QuietFlag",
    "clean_json",
    "console",
    "fail_on_stemmap_error",
    "json_default",
    "out",
    "print_error",
    "progress",
]

#: diagnostics, warnings and progress go to stderr
console = Console(stderr=True)
#: results (tables, summaries) go to stdout
out = Console()


#: ``-q/--quiet``, the same option on every command that prints progress or a summary: the
#: command runs and writes its products as without it, but prints no progress bar, no
#: first-run notice and no summary. Errors and warnings still go to stderr (and the exit code
#: is unchanged); a ``--json`` object is still printed (it is the output asked for).
QuietFlag = Annotated[
    bool,
    typer.Option(
        "--quiet",
        "-q",
        help="Print no progress bar, first-run notice or summary. Errors and warnings still "
        "go to stderr; where the command has --json, its object is still printed.",
    ),
]

#: ``--progress/--no-progress`` of the long-running folder commands (``map``, ``demo``):
#: only the progress bars; ``-q`` turns them off too.
ProgressFlag = Annotated[
    bool,
    typer.Option(
        "--progress/--no-progress",
        help="Show progress bars on stderr (-q/--quiet turns them off too).",
    ),
]


def print_error(message: str) -> None:
    """One ``error: ...`` line on stderr, never wrapped and never read as rich markup."""
    console.print(f"[red]error:[/red] {escape(message)}", soft_wrap=True)


@contextlib.contextmanager
def fail_on_stemmap_error() -> Iterator[None]:
    """Turn a StemmapError or an OS error into one ``error:`` line and exit code 2.

    The line is printed unwrapped (``soft_wrap``), so a long path stays on one line and tools
    can ``grep '^error:'``. OS errors (a failed read or write that no reader wrapped) name the
    file and the reason; no traceback is shown.
    """
    try:
        yield
    except StemmapError as exc:
        print_error(str(exc))
        raise typer.Exit(code=2) from exc
    except MemoryError as exc:
        print_error(
            "out of memory: the input is too large for this machine (see docs/reliability.md)."
        )
        raise typer.Exit(code=2) from exc
    except OSError as exc:
        where = f" {os.fsdecode(exc.filename)!r}" if exc.filename is not None else ""
        print_error(f"cannot access{where}: {exc.strerror or exc}.")
        raise typer.Exit(code=2) from exc


def progress(enabled: bool = True) -> Progress:
    """A rich progress bar on stderr; disabled (silent) when ``enabled`` is False."""
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeRemainingColumn(),
        console=console,
        disable=not enabled,
        transient=True,
    )


def clean_json(v: Any) -> Any:
    """JSON has no NaN/inf: replace them by null, recursively."""
    if isinstance(v, dict):
        return {k: clean_json(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [clean_json(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


def json_default(v: Any) -> Any:
    """``json.dump(default=...)`` for numpy scalars and arrays."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f"cannot serialise {type(v).__name__}")
