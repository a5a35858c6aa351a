"""Every ``--help`` text renders whole: the CLI uses typer's markdown mode, which drops
anything that looks like an HTML tag (``<log>``, ``<out>``) from option and command help."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

import typer
from typer.testing import CliRunner

from stemmap.cli import app

runner = CliRunner()
_TAG = re.compile(r"</?[A-Za-z][^<>]*>")


def _commands(cmd: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    yield path, cmd
    for name, sub in getattr(cmd, "commands", {}).items():  # a group (typer's own click)
        yield from _commands(sub, (*path, name))


def test_no_help_text_holds_a_tag_that_markdown_would_drop():
    found = []
    n_params = 0
    for path, cmd in _commands(typer.main.get_command(app)):
        texts = [("(command)", cmd.help or "")]
        texts += [(p.name, getattr(p, "help", None) or "") for p in cmd.params]
        found += [(" ".join(path), name, m) for name, t in texts for m in _TAG.findall(t)]
        n_params += len(cmd.params)
    assert n_params > 100  # the walk reached every subcommand's options
    assert not found, f"markdown drops these from --help: {found}"


def test_placeholders_reach_the_rendered_help():
    env = {"COLUMNS": "250"}
    out = runner.invoke(app, ["detect", "--help"], env=env).output
    assert "OUT/LOG/observations.csv" in out
    # the example and the --rejected sentence are two paragraphs, not one run-on line
    assert re.search(r"--preset stemmap\s*\n", out)
    out = runner.invoke(app, ["sim", "scans", "--help"], env=env).output
    assert "stem + _trees.csv" in out and "stem + _poses.csv" in out
    assert "-30..30" in runner.invoke(app, ["harvest-sim", "--help"], env=env).output
