"""The ``stemmap`` typer application: every command registered (imported by
:func:`stemmap.cli.main` once its signal handling is in place).

Each area registers its commands from its own module (``cli/_<area>.py``, a ``register(app)``
function), so the entry point stays small and areas do not edit each other's code.
"""

from __future__ import annotations

import importlib
import logging
import sys
from typing import Any

import typer
from typer.core import TyperGroup

__all__ = ["app"]


def _click_exception() -> type[Exception]:
    """click's ClickException (typer >= 0.20 vendors click as ``typer._click``)."""
    for mod in ("typer._click.exceptions", "click.exceptions"):
        try:
            cls: type[Exception] = importlib.import_module(mod).ClickException
        except (ImportError, AttributeError):
            continue
        return cls
    raise ImportError("click's ClickException not found")  # pragma: no cover


class _PlainErrorGroup(TyperGroup):
    """typer's group, but a usage error is one unwrapped ``error:`` line (not a rich panel).

    A rich panel wraps a long message over several boxed lines, which breaks ``grep
    '^error:'`` and copy-paste of paths (issue 13). Help output keeps rich formatting.
    """

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        kwargs["standalone_mode"] = False
        if not standalone_mode:
            return super().main(*args, **kwargs)
        from stemmap.cli._common import console, print_error

        try:
            rv = super().main(*args, **kwargs)
        except _click_exception() as caught:
            exc: Any = caught
            if type(exc).__name__ == "NoArgsIsHelpError":  # help was asked for: typer shows it
                from typer import rich_utils

                rich_utils.rich_format_error(exc)
                sys.exit(exc.exit_code)
            ctx = getattr(exc, "ctx", None)
            if ctx is not None:
                console.print(ctx.get_usage(), markup=False, soft_wrap=True, highlight=False)
                if ctx.command.get_help_option(ctx) is not None:
                    console.print(
                        f"Try '{ctx.command_path} {ctx.help_option_names[0]}' for help.",
                        markup=False,
                        soft_wrap=True,
                        highlight=False,
                    )
            print_error(exc.format_message())
            sys.exit(exc.exit_code)
        except typer.Abort:
            console.print("Aborted!", markup=False)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)

    def invoke(self, ctx: Any) -> Any:
        """Ctrl-C: one ``error:`` line like SIGTERM's (typer then exits with 130); before,
        an interrupted run ended with an empty line, not saying its products were dropped."""
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            from stemmap.cli._common import print_error

            print_error("interrupted (Ctrl-C); the products of this run were not written.")
            raise


app = typer.Typer(
    cls=_PlainErrorGroup,
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
    "stemmap.cli._odometry",
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
