"""Give freed heap memory back to the operating system during long runs (glibc only).

glibc's ``malloc`` keeps memory that was freed inside its arenas: below chunks still in use,
and at the top of the heap up to ``M_TRIM_THRESHOLD``, which glibc raises (to twice the
block) whenever a large mmapped block is freed (dynamic thresholds). On a long SLAM run
(issue 13's 10x Victoria Park replay) the resident set size then follows the arenas' size,
which keeps every transient peak, in steps, not the bytes in use (``mallinfo2``).
``malloc_trim(0)`` releases every free page of every arena (``madvise(MADV_DONTNEED)``,
glibc >= 2.8), so RSS follows the heap in use. It changes no value the program computes,
only which pages stay resident.

:class:`HeapTrimmer` calls it at most once per ``min_interval_s`` seconds of the process's
CPU time (:func:`time.process_time`: the cost stays a fixed share of the work, however
loaded the machine), from a callback the caller already makes often (``stemmap map`` wraps
the back-end's progress callback). One trim of the 10x soak's ~230 MB heap costs ~1 ms.
Where ``malloc_trim`` is missing (not Linux, musl, macOS, Windows) :func:`malloc_trim` is a
no-op returning False.

References: glibc manual, "Memory Allocation Tunables" and ``malloc_trim(3)``.
"""

from __future__ import annotations

import ctypes
import math
import sys
import time
from collections.abc import Callable
from functools import cache

__all__ = ["TRIM_INTERVAL_S", "HeapTrimmer", "malloc_trim"]

#: Least CPU time (s) between two trims of the long loops that trim (``stemmap map``'s
#: progress callback, :class:`stemmap.slam.graph.Isam2Slam`'s keyframe loop).
TRIM_INTERVAL_S = 0.2

# process CPU time of the last trim by any trimmer on the default clock (shared, so nested
# trimmers -- a back-end's own inside ``stemmap map``'s progress callback -- trim no more
# often than one of them would)
_last_shared = [-math.inf]


@cache
def _libc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim`` from the running process, or None where it is missing."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None).malloc_trim  # the C library the interpreter is linked with
    except (OSError, AttributeError):  # musl and other C libraries have no malloc_trim
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


def malloc_trim() -> bool:
    """Release the free pages of every malloc arena to the OS (``malloc_trim(0)``).

    Returns
    -------
    bool
        True if glibc returned memory; False if there was none to return or the platform has
        no ``malloc_trim`` (then nothing is done).
    """
    fn = _libc_trim()
    return bool(fn(0)) if fn is not None else False


class HeapTrimmer:
    """A callable that runs :func:`malloc_trim` at most once per ``min_interval_s`` seconds.

    Parameters
    ----------
    min_interval_s : float, >= 0, seconds
        Least time on ``clock`` between two trims (the first call trims only once this much
        time has passed since construction). 0 trims on every call.
    clock : callable, optional
        Non-decreasing seconds (default :func:`time.process_time`, CPU time of the process;
        a test passes its own). Trimmers on the default clock share their last trim: a
        back-end that trims its own loop, run from a caller whose progress callback trims
        too, trims no more often than one of them alone.
    trim : callable, optional
        The trim itself (default :func:`malloc_trim`).

    Attributes
    ----------
    n_trims : int
        Trims run so far.

    Examples
    --------
    >>> t = iter([0.0, 1.0, 5.0, 6.0, 11.0])
    >>> trimmer = HeapTrimmer(5.0, clock=lambda: next(t), trim=lambda: True)
    >>> [trimmer() for _ in range(4)]
    [False, True, False, True]
    >>> trimmer.n_trims
    2
    >>> HeapTrimmer(-1.0)
    Traceback (most recent call last):
    ...
    ValueError: min_interval_s must be a finite number >= 0 (seconds), got -1.0.
    """

    def __init__(
        self,
        min_interval_s: float = 0.2,
        *,
        clock: Callable[[], float] = time.process_time,
        trim: Callable[[], bool] = malloc_trim,
    ) -> None:
        if not min_interval_s >= 0.0 or min_interval_s == float("inf"):
            raise ValueError(
                f"min_interval_s must be a finite number >= 0 (seconds), got {min_interval_s}."
            )
        self.min_interval_s = float(min_interval_s)
        self._clock = clock
        self._trim = trim
        self._shared = clock is time.process_time
        self._last = clock()
        self.n_trims = 0

    def __call__(self) -> bool:
        """Trim if ``min_interval_s`` passed since the last trim; True if it trimmed."""
        now = self._clock()
        last = max(self._last, _last_shared[0]) if self._shared else self._last
        if now - last < self.min_interval_s:
            return False
        self._last = now
        if self._shared:
            _last_shared[0] = now
        self.n_trims += 1
        self._trim()
        return True
