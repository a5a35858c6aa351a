"""Atomic file writes: write to a temporary file beside the target, then rename over it.

An interrupted run never leaves a half-written product behind. Products are also durable
(the data is fsynced before the rename, so after a power loss the file holds either the old
or the new content); scratch files that a later step re-checks may skip that
(``durable=False``, docs/reliability.md).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_write", "umask_mode"]


def umask_mode(base: int) -> int:
    """``base`` less the process umask: the permissions ``open()`` (``base`` 0o666) or
    ``mkdir()`` (0o777) would give a new file or folder. ``mkstemp`` / ``mkdtemp`` create
    0600 / 0700 ones; a product renamed into place from one gets these bits instead."""
    umask = os.umask(0)
    os.umask(umask)
    return base & ~umask


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike[str], mode: str = "w", *, durable: bool = True, **kwargs: Any
) -> Iterator[IO[Any]]:
    """Open a temporary file for writing; on success rename it to ``path``, on error delete it.

    ``mode`` is ``"w"`` (text, UTF-8 by default) or ``"wb"``. Parent folders are created.
    ``durable``: fsync the data before the rename (the default, for products). Without it
    the rename still makes the file appear whole to every reader while the system runs, but
    after a power loss or kernel crash it may be missing, empty or old: only for scratch
    files that are deleted, rewritten or verified by hash before they are trusted again
    (the scale-out engine's chunk results and stage files). It saves the write-back a
    fsync forces -- data that is deleted soon may never reach the disk.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write supports modes 'w' and 'wb', got {mode!r}.")
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    # mkstemp creates 0600 files; a product should get the permissions a plain open() would
    # give (an existing file's mode, else 0666 less the umask), so other tools and users can read it
    try:
        mode_bits = target.stat().st_mode & 0o7777
    except FileNotFoundError:
        mode_bits = umask_mode(0o666)
    os.fchmod(fd, mode_bits)
    if mode == "w":
        kwargs.setdefault("encoding", "utf-8")
        kwargs.setdefault("newline", "")
    try:
        with os.fdopen(fd, mode, **kwargs) as fh:
            yield fh
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
