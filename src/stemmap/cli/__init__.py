"""The ``stemmap`` command-line interface (typer).

Each area registers its commands from its own module (``cli/_<area>.py``, a ``register(app)``
function), so the entry point stays small and areas do not edit each other's code.
"""

from __future__ import annotations

import importlib
import logging

import typer

__all__ = ["app", "main"]

app = typer.Typer(
    name="stemmap",
    help=(
        "Tree stem maps from 2D laser scans, 3D point clouds, camera images and odometry.\n\n"
        "Start with `stemmap demo`: it simulates a forest, detects every trunk and writes a map."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="markdown",
)

#: Modules under stemmap.cli that define ``register(app)``; one per area.
_COMMAND_MODULES: tuple[str, ...] = (
    "stemmap.cli._demo",
    "stemmap.cli._harvest",
    "stemmap.cli._detect",
    "stemmap.cli._sim",
    "stemmap.cli._io",
    "stemmap.cli._stems",
    "stemmap.cli._vision",
    "stemmap.cli._map",
)


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details."),
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


for _name in _COMMAND_MODULES:
    importlib.import_module(_name).register(app)


def main() -> None:
    """Console-script entry point."""
    app()
