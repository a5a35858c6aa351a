"""What the running CLI command was given: its parsed parameters, and which option named a path.

:mod:`stemmap.io.products` refuses outputs (an output on an input, two outputs on one file, ...)
for every command in one place. Its messages name the command-line option that gave each path
(``--rejected 'a.csv' is the same file as the input SCANS 'a.csv'``), so the user knows which
argument to change without patching each command's messages. The option is looked up in the
current click context (typer runs on click); outside a command (library use, a worker process)
there is none and the messages say ``output`` / ``input``.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["PathNames", "cli_parameters"]


def _context() -> Any:
    """The current click context, or None outside a command."""
    for mod in ("typer._click.globals", "click.globals"):  # typer >= 0.20 vendors click
        with contextlib.suppress(ImportError, AttributeError):
            ctx = importlib.import_module(mod).get_current_context(silent=True)
            if ctx is not None:
                return ctx
    return None


def cli_parameters() -> dict[str, Any]:
    """The parsed options of the running CLI command ({} outside a command), JSON-ready."""
    ctx = _context()
    if ctx is None:
        return {}
    return {k: json.loads(json.dumps(v, default=str)) for k, v in ctx.params.items()}


def _label(param: Any) -> str:
    """How ``--help`` names a parameter: an option's long flag, an argument's metavar/NAME."""
    opts = [o for o in getattr(param, "opts", []) if isinstance(o, str)]
    if getattr(param, "param_type_name", "") == "option" and opts:
        return max(opts, key=len)  # "--out" rather than "-o"
    metavar = getattr(param, "metavar", None)
    return str(metavar) if metavar else str(param.name).upper()


def _paths(value: Any, *, text: bool) -> list[tuple[Any, Path]]:
    """``(value as given, as a Path)`` for a path parameter's value or each of its values;
    ``text``: strings too (an argument taking paths or globs as ``str``, ``stems CLOUDS``)."""
    values = value if isinstance(value, (list, tuple)) else [value]
    kinds = (os.PathLike, str) if text else (os.PathLike,)
    return [(v, Path(v)) for v in values if isinstance(v, kinds)]


def _same(a: Path, b: Path) -> bool:
    if a == b:
        return True
    with contextlib.suppress(OSError, RuntimeError):
        return a.absolute() == b.absolute() or a.resolve() == b.resolve()
    return False


def _inside(child: Path, folder: Path) -> bool:
    try:
        child.absolute().relative_to(folder.absolute())
    except (OSError, ValueError):
        return False
    return True


#: role of a parameter's path in the run: "input", "output" or "" (not given to the run)
Role = str


@dataclass(frozen=True)
class PathNames:
    """The path-valued parameters of a command: ``(label, path, role)`` in ``--help`` order.

    ``label`` is an option's long flag (``--rejected``) or an argument's name (``SCANS``);
    ``role`` says whether the run was given that very value as an input or an output, which
    decides the name when one path is typed for both (``detect a.npz --rejected a.npz``).
    Build it with :meth:`from_context` while the command runs.
    """

    given: tuple[tuple[str, Path, Role], ...] = ()

    @classmethod
    def from_context(
        cls, inputs: Iterable[object] = (), outputs: Iterable[object] = ()
    ) -> PathNames:
        """The running command's path parameters (none outside a command).

        ``inputs`` / ``outputs``: the objects the command passed to the run; a parameter whose
        value *is* one of them (the same object typer handed the command) takes that role.
        """
        ctx = _context()
        if ctx is None:
            return cls()
        ins, outs = {id(o) for o in inputs}, {id(o) for o in outputs}
        rows: list[tuple[str, Path, Role]] = []
        for param in getattr(ctx.command, "params", []):
            is_argument = getattr(param, "param_type_name", "") == "argument"
            for raw, p in _paths(ctx.params.get(param.name), text=is_argument):
                role = "output" if id(raw) in outs else "input" if id(raw) in ins else ""
                rows.append((_label(param), p, role))
        return cls(tuple(rows))

    def options(self, path: Path, role: Role = "") -> list[str]:
        """Labels of every parameter naming ``path`` (same text, else same absolute path or
        target), those of ``role`` first (stable: ``--help`` order within a rank)."""
        rows = [r for r in self.given if r[1] == path] or [
            r for r in self.given if _same(r[1], path)
        ]
        # the role asked for first, then parameters the run was not given, then the other role
        rows.sort(key=lambda r: 0 if r[2] == role else 2 if r[2] and role else 1)
        return list(dict.fromkeys(r[0] for r in rows))

    def _folder(self, path: Path) -> tuple[str, Path] | None:
        """The parameter whose folder holds ``path`` (``map --out DIR``, ``stems DIR``)."""
        held = [(lab, p) for lab, p, _ in self.given if p != path and _inside(path, p)]
        return max(held, key=lambda lp: len(lp[1].absolute().parts), default=None)

    def named(self, path: Path, role: Role = "") -> str:
        """``--out 'x'`` for a path an option gave, else ``'x'`` (with the folder holding it)."""
        labels = self.options(path, role)
        if labels:
            return f"{labels[0]} {str(path)!r}"
        held = self._folder(path)
        where = "" if held is None else f" (in {held[0]} {str(held[1])!r})"
        return f"{str(path)!r}{where}"

    def output(self, path: Path) -> str:
        """``--rejected 'a.csv'``; ``output 'd/x.csv' (in --out 'd')``; ``output 'x.csv'``."""
        shown = self.named(path, "output")
        return shown if self.options(path) else f"output {shown}"

    def input(self, path: Path, what: str = "input") -> str:
        """``the input SCANS 'a.npz'``, ``the input --imu 'imu.csv'``, ``the input 'x'``."""
        return f"the {what} {self.named(path, 'input')}"

    def outputs(self, paths: Sequence[Path]) -> list[str]:
        """Names of outputs that are one file: each option naming it once, then the rest
        (``--out 'a.csv'``, ``--rejected 'a.csv'``; ``--trees-out 'p.csv'``, ``output 'p.csv'``)."""
        used: list[str] = []
        names: list[str] = []
        for p in paths:
            label = next((lab for lab in self.options(p, "output") if lab not in used), None)
            if label is None:
                names.append(f"output {str(p)!r}")
            else:
                used.append(label)
                names.append(f"{label} {str(p)!r}")
        return names
