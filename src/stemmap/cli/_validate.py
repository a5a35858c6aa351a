"""Shared validation of numeric CLI options: one helper, one message form (issue 13).

``typer.Option(callback=bounded("--speed", gt=0))`` makes a bad value a usage error (exit 2)
that names the option and the valid range, e.g.::

    error: Invalid value for --speed: got 0.0, but it must be a finite number > 0.

NaN and infinities are refused unless ``finite=False``. ``None`` (an option left unset) passes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, TypeVar

import typer

__all__ = ["bounded", "range_text"]

T = TypeVar("T", int, float, int | None, float | None)


def range_text(
    *,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    integer: bool = False,
) -> str:
    """'a whole number >= 1', 'a finite number in (0, 1]', ... for the error message."""
    kind = "a whole number" if integer else "a finite number"
    lo = (gt, "(") if gt is not None else (ge, "[") if ge is not None else None
    hi = (lt, ")") if lt is not None else (le, "]") if le is not None else None
    if lo and hi:
        return f"{kind} in {lo[1]}{lo[0]:g}, {hi[0]:g}{hi[1]}"
    if lo:
        return f"{kind} {'>' if lo[1] == '(' else '>='} {lo[0]:g}"
    if hi:
        return f"{kind} {'<' if hi[1] == ')' else '<='} {hi[0]:g}"
    return kind


def bounded(
    option: str,
    *,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    finite: bool = True,
) -> Callable[[Any], Any]:
    """A typer callback refusing values outside the range (and NaN/inf when ``finite``).

    Parameters
    ----------
    option : str
        The option's name as the user types it (``"--n-trees"``), for the message.
    ge, gt, le, lt : float, optional
        Inclusive / exclusive lower and upper bounds.
    finite : bool
        Refuse NaN and +-inf (default).
    """

    def check(value: Any) -> Any:
        if value is None:
            return value
        integer = isinstance(value, int) and not isinstance(value, bool)
        v = float(value)
        ok = not (finite and not math.isfinite(v)) and not math.isnan(v)
        ok = ok and (ge is None or v >= ge) and (gt is None or v > gt)
        ok = ok and (le is None or v <= le) and (lt is None or v < lt)
        if not ok:
            want = range_text(ge=ge, gt=gt, le=le, lt=lt, integer=integer)
            raise typer.BadParameter(
                f"{value!r} is out of range; it must be {want}.", param_hint=option
            )
        return value

    return check
