"""Helpers shared by CLI commands: error reporting and progress bars (rich, CLI only)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from stemmap.errors import StemmapError

__all__ = ["console", "fail_on_stemmap_error", "out", "progress"]

#: diagnostics, warnings and progress go to stderr
console = Console(stderr=True)
#: results (tables, summaries) go to stdout
out = Console()


@contextlib.contextmanager
def fail_on_stemmap_error() -> Iterator[None]:
    """Turn a StemmapError into a one-line message and exit code 2 (no traceback)."""
    try:
        yield
    except StemmapError as exc:
        console.print(f"[red]error:[/red] {exc}")
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
