"""The read budget: how much memory a reader may allocate for one input file (private).

A file can announce far more data than it stores -- honestly. An NPZ's deflate stream expands
up to 1032:1 (a 20 MB file of zeros holds 20 GB of array), a LAS header names a point count,
a bag message an array length, a camera frame its pixel count. When the announcement is
consistent (no damage to detect), the only defence left is to compare what the reader is about
to allocate with the memory the machine has, and refuse *before* allocating: one ``error:``
line naming the file and the size, instead of minutes of swapping and the kernel's OOM killer
(which on a shared machine may kill another program).

The budget is :data:`BUDGET_FRACTION` of the memory available when the check runs (Linux
``MemAvailable`` from ``/proc/meminfo``, lowered to the cgroup's ``memory.max`` minus its
usage and to ``RLIMIT_AS`` minus the process's mapped size (``VmSize``) when those are
tighter), but never less than :data:`BUDGET_FLOOR_BYTES`, so an ordinary file still loads on
a busy or small machine. Half:
a reader's arrays are not the whole run (a cloud is sorted, gridded and copied afterwards;
``stemmap stems`` peaks at ~3x the raw xyz of a plot). The environment variable
:data:`BUDGET_ENV` (gigabytes, e.g. ``STEMMAP_MAX_READ_GB=40``) replaces the budget, in either
direction; ``0`` or ``inf`` turns the check off.
"""

from __future__ import annotations

import math
import os
import resource
from dataclasses import dataclass
from pathlib import Path

from stemmap.errors import ConfigError, InputError

__all__ = [
    "BUDGET_ENV",
    "BUDGET_FLOOR_BYTES",
    "BUDGET_FRACTION",
    "ReadLimitError",
    "available_memory",
    "check_read_budget",
    "human_bytes",
    "read_budget",
]

#: Environment variable (GB) that replaces the computed budget; 0 or inf disables the check.
BUDGET_ENV = "STEMMAP_MAX_READ_GB"
#: Share of the available memory one input file may take.
BUDGET_FRACTION = 0.5
#: The budget is never below this (1 GiB), whatever the machine reports.
BUDGET_FLOOR_BYTES = 1 << 30


class ReadLimitError(InputError):
    """An input needs more memory (or, for a bag inflated to a temporary file, disk) than the
    read limit allows: a refusal, not damage (a bag reader stops on it instead of skipping the
    rest of a topic as damaged)."""


def human_bytes(n: float) -> str:
    """``n`` bytes as ``'20 GB'`` / ``'512 kB'`` (decimal units, 3 significant digits)."""
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} bytes"


def _proc_kb(path: str, key: str) -> int | None:
    """Bytes of the ``key:`` line of a Linux ``/proc`` file that counts in kB (``MemAvailable``
    of ``/proc/meminfo``, ``VmSize`` of ``/proc/self/status``), None if unknown."""
    try:
        text = Path(path).read_text()
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith(key + ":"):
            parts = line.split()
            if len(parts) >= 2 and parts[1].isdigit():
                return int(parts[1]) * 1024
    return None


def _meminfo_available() -> int | None:
    return _proc_kb("/proc/meminfo", "MemAvailable")


def _cgroup_room() -> int | None:
    """Bytes left below the cgroup's memory limit (v2 ``memory.max``, v1 ``limit_in_bytes``)."""
    for limit_file, usage_file in (
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
        (
            "/sys/fs/cgroup/memory/memory.limit_in_bytes",
            "/sys/fs/cgroup/memory/memory.usage_in_bytes",
        ),
    ):
        try:
            limit = Path(limit_file).read_text().strip()
            usage = Path(usage_file).read_text().strip()
        except OSError:
            continue
        if not limit.isdigit() or not usage.isdigit():
            continue  # "max": no limit
        if int(limit) >= 1 << 60:  # cgroup v1's "no limit" is a huge number
            continue
        return max(int(limit) - int(usage), 0)
    return None


def _mapped_bytes() -> int | None:
    """The address space this process has mapped now (Linux ``VmSize``), None if unknown."""
    return _proc_kb("/proc/self/status", "VmSize")


def _address_space_room() -> int | None:
    """Bytes of address space left below ``RLIMIT_AS`` (soft): the limit less what the process
    has mapped already (``ulimit -v`` counts every mapping, not only the pages in use); the
    limit itself where the mapped size cannot be read. None without a limit."""
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None
    mapped = _mapped_bytes()
    return int(soft) if mapped is None else max(int(soft) - mapped, 0)


def available_memory() -> int | None:
    """Bytes a new allocation can take now: the least of MemAvailable, the cgroup's room and
    the room below ``RLIMIT_AS``; None where none of them can be read (not Linux)."""
    sources = (_meminfo_available(), _cgroup_room(), _address_space_room())
    known = [v for v in sources if v is not None]
    if not known:
        try:  # POSIX fallback: free physical pages
            pages = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return None
        return int(pages) if pages > 0 else None
    return min(known)


def read_budget() -> tuple[float, str]:
    """(bytes one input file may allocate, how that number was chosen) -- see the module."""
    env = os.environ.get(BUDGET_ENV, "").strip()
    if env:
        try:
            gb = float(env)
        except ValueError:
            raise ConfigError(
                f"{BUDGET_ENV}={env!r} is not a number of gigabytes (e.g. {BUDGET_ENV}=40)."
            ) from None
        if math.isnan(gb) or gb < 0:
            raise ConfigError(f"{BUDGET_ENV}={env!r} must be >= 0 GB (0 turns the limit off).")
        if gb == 0 or math.isinf(gb):
            return math.inf, f"{BUDGET_ENV}={env}"
        return gb * 1e9, f"set by {BUDGET_ENV}={env}"
    avail = available_memory()
    if avail is None:
        return math.inf, "available memory unknown"
    budget = max(BUDGET_FRACTION * avail, BUDGET_FLOOR_BYTES)
    return budget, f"{BUDGET_FRACTION:.0%} of the {human_bytes(avail)} of memory available now"


def check_read_budget(nbytes: float, path: str | os.PathLike[str], what: str, detail: str) -> None:
    """Refuse to allocate ``nbytes`` for reading ``path`` if that exceeds :func:`read_budget`.

    Parameters
    ----------
    nbytes : bytes the reader is about to allocate (announced by the file, not yet allocated)
    path, what : the file and what it is (``"scan NPZ"``), for the message
    detail : what announces the size, with the size (``"its arrays hold 20 GB when
        decompressed"``)

    Raises
    ------
    InputError
        Naming the file, the size, the limit, how it was chosen and how to raise it.
    """
    if not over_read_budget(nbytes):
        return
    raise ReadLimitError(f"{what} {os.fspath(path)!r}: {read_limit_text(nbytes, detail)}")


def over_read_budget(nbytes: float) -> bool:
    """True if ``nbytes`` exceed :func:`read_budget`. Cheap when the answer cannot be yes
    (no ``STEMMAP_MAX_READ_GB`` and ``nbytes`` under the 1 GiB floor: no /proc read), so a
    reader may call it once per message."""
    if nbytes <= BUDGET_FLOOR_BYTES and not os.environ.get(BUDGET_ENV, "").strip():
        return False
    return nbytes > read_budget()[0]


def read_limit_text(
    nbytes: float,
    detail: str,
    *,
    partial: bool = False,
    limit: tuple[float, str] | None = None,
) -> str:
    """``detail``, the read limit and how to raise it: the body of a refusal (the caller puts
    the file's name in front). ``partial``: ``nbytes`` is what was counted before the read
    stopped, the whole needs more (the value suggested is a lower bound). ``limit``: the
    :func:`read_budget` the caller compared with (default: computed now)."""
    budget, why = read_budget() if limit is None else limit
    need_gb = math.ceil(nbytes / 1e9 * 1.1 * 10) / 10  # 10 % headroom, one decimal
    raise_to = (
        f"{BUDGET_ENV} above {need_gb:g}" if partial else f"the limit: {BUDGET_ENV}={need_gb:g}"
    )
    return (
        f"{detail}; that is more than stemmap's read limit of {human_bytes(budget)} ({why}). "
        f"If the file is genuine and the machine has the memory, raise {raise_to} "
        "(gigabytes; 0 turns it off)."
    )


#: The longest line a line-oriented numeric text file (CSV, XYZ) may have: 1 MB (a scan CSV
#: row of 10,000 beams is ~100 kB). A longer line is not a row of numbers a reader can use,
#: and splitting it into fields allocated ~30x its size (one Python str per field).
MAX_LINE_BYTES = 1 << 20

_BLOCK = 1 << 24


@dataclass(frozen=True, slots=True)
class TextStats:
    """Size, line count and longest line (length, 1-based number) of a text file, from one
    streaming pass."""

    size: int
    lines: int
    longest: int
    longest_line: int


def text_stats(path: str | os.PathLike[str]) -> TextStats:
    """One pass over ``path`` in 16 MB blocks (no more memory than that): its size, number of
    lines and the length and 1-based number of its longest line."""
    import numpy as np

    size = lines = longest = longest_line = 0
    run = 0  # length of the line in progress at the end of the previous block
    with open(path, "rb") as fh:
        while block := fh.read(_BLOCK):
            size += len(block)
            nl = np.flatnonzero(np.frombuffer(block, np.uint8) == 10)
            if nl.size == 0:
                run += len(block)
                continue
            first = run + int(nl[0])
            gaps = np.diff(nl) - 1
            if first >= longest:
                longest, longest_line = first, lines + 1
            if gaps.size and int(gaps.max()) > longest:
                k = int(np.argmax(gaps))
                longest, longest_line = int(gaps[k]), lines + k + 2
            lines += int(nl.size)
            run = len(block) - int(nl[-1]) - 1
    if run:
        lines += 1
        if run > longest:
            longest, longest_line = run, lines
    return TextStats(size, lines, longest, longest_line)


def check_text_budget(
    path: str | os.PathLike[str],
    what: str,
    *,
    per_byte: float,
    per_line: float,
    max_line: int | None = MAX_LINE_BYTES,
) -> TextStats:
    """Refuse a text file whose parse would exceed the read budget, or with a line longer
    than ``max_line`` bytes (None: no line limit, e.g. JSON), before reading it.

    The parse's memory is estimated as ``per_byte`` x the file size + ``per_line`` x its line
    count: each reader's Python objects per line (a str, a tuple, list slots: ~200 B for
    :func:`stemmap.io._util.parse_numeric_csv`) dominate a file of short lines, its text and
    numbers a file of long ones.

    Raises
    ------
    InputError
        Naming the file, the line (too long) or the estimate and the limit (too large).
    """
    st = text_stats(path)
    if max_line is not None and st.longest > max_line:
        raise InputError(
            f"{what} {os.fspath(path)!r} line {st.longest_line} is {human_bytes(st.longest)} "
            f"long; a line of this file holds a few numbers (at most {human_bytes(max_line)}): "
            "is it the right file, or binary data?"
        )
    need = per_byte * st.size + per_line * st.lines
    check_read_budget(
        need,
        path,
        what,
        f"{human_bytes(st.size)} in {st.lines:,} lines needs ~{human_bytes(need)} to parse",
    )
    return st
