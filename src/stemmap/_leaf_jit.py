"""``leaf_njit``: numba's ``njit`` for kernels that allocate nothing and return no array.

numba's runtime (NRT) counts references to every array: a compiled function increments the
count of each array argument on entry and of each view it makes (a slice, a row), and
decrements them on exit, each time with an atomic (``lock``-prefixed) instruction. A small
kernel called millions of times pays these far more than its arithmetic: sampled with
``perf record`` on the ``stemmap`` preset's 361-beam batch, ``NRT_incref`` / ``NRT_decref``
took 57 % of the detector's CPU time and 65 % of the circle fit's (the Levenberg-Marquardt
cost function increments 10 arguments per call and 2 more per return;
docs/algorithms/scan-detection.md, "Speed").

A kernel that allocates nothing and returns no array needs no counting: its caller holds a
reference to every array it is given, and a view it makes dies with it. ``leaf_njit`` compiles
such kernels without the NRT (numba's ``_nrt=False`` flag): the machine code of the arithmetic
is the same, so results are the same to the bit (tests/scan/test_detect_fast.py's digests).
A kernel compiled this way must not allocate (numba refuses to compile it) and must not return
an array or store one where it outlives the call (the caller would release a reference it was
never given). numba compiles a callee with its caller's setting unless the callee states its
own: a kernel that allocates and is called from a leaf kernel is compiled with
:func:`nrt_njit`, which keeps the runtime. Where numba lacks the flag (a private option), the
kernels compile as ordinary ``njit`` ones: the same results, slower.

numba's on-disk cache key holds a kernel's signature, target and bytecode but not its compile
options: an edit of this file alone would leave kernels compiled under the old flags in the
cache. Every module whose cached kernels use these decorators (or compile in kernels that do)
calls :func:`stemmap._numba_cache.drop_stale_cache` at import, which hashes this file
(tests/test_numba_cache.py checks that none is missed).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from numba import njit
from numba.core import options as _options

__all__ = ["leaf_njit", "nrt_njit"]

#: numba accepts the (private) ``_nrt`` target option
HAS_NRT_FLAG = hasattr(_options.DefaultOptions, "_nrt")


def _jit(inline: str, nrt: bool) -> Callable[[Any], Any]:
    """``njit`` with this module's options (typed loosely: ``_nrt`` is not in numba's stubs)."""
    options: dict[str, Any] = {"cache": True, "error_model": "numpy", "inline": inline}
    if HAS_NRT_FLAG:
        options["_nrt"] = nrt
    jit: Any = njit
    return jit(**options)


def leaf_njit(*, inline: str = "never") -> Callable[[Any], Any]:
    """``njit(cache=True, error_model="numpy", inline=inline)`` without reference counting
    (see the module docstring for the kernels it is meant for)."""
    return _jit(inline, False)


def nrt_njit(*, inline: str = "never") -> Callable[[Any], Any]:
    """``njit(cache=True, error_model="numpy", inline=inline)`` with reference counting stated
    explicitly: for kernels that allocate and are called from a :func:`leaf_njit` kernel (numba
    would otherwise compile them without the runtime, as their caller, and refuse)."""
    return _jit(inline, True)
