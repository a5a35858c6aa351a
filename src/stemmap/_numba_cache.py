"""Keep numba's on-disk cache honest about cross-module kernels.

numba's cache (``@njit(cache=True)``) of a module is keyed on that module's own source file
(modification time and size). A kernel that calls an ``@njit`` function of another module, or
reads another module's constant, has that code and value compiled *into* it, so after an
edit of the other module -- or a ``git pull`` into an editable install -- the stale machine
code would keep running without any error. :func:`drop_stale_cache` records a hash of the
dependency files next to the cache and deletes the dependent module's cache entries when the
hash changes, so the next call recompiles.

The compile flags are a dependency of every such module: numba's cache key holds the
signature, the target machine and the function's bytecode, but not its compile options, and
:mod:`stemmap._leaf_jit` sets one of them (``_nrt``, reference counting on or off) for the
kernels of ``leaf_njit`` / ``nrt_njit`` -- and, by inlining and linking, for every kernel that
calls them. An edit of that file alone (a kernel moved between the two, the flag's default)
would leave machine code compiled under the old flags in the cache, so :func:`drop_stale_cache`
always hashes it (:data:`FLAGS_FILE`) with the listed dependencies.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path
from typing import Any

__all__ = ["drop_stale_cache"]

log = logging.getLogger(__name__)

#: The compile-flag module every caller's kernels are compiled with (module docstring): part of
#: every dependency hash.
FLAGS_FILE = Path(__file__).with_name("_leaf_jit.py")


def _cache_dir(dispatcher: Any, module_file: Path) -> Path:
    """Where numba keeps ``dispatcher``'s cache (``__pycache__`` beside the module, or the
    user-wide / ``NUMBA_CACHE_DIR`` location numba chose when that is not writable)."""
    cache = getattr(dispatcher, "_cache", None)
    path = getattr(cache, "_cache_path", None)  # numba internals: fall back if they change
    return Path(path) if path else module_file.parent / "__pycache__"


def drop_stale_cache(dispatcher: Any, module_file: str, *deps: str) -> bool:
    """Delete the cache entries of ``module_file``'s kernels if any of ``deps`` or the
    compile-flag module :data:`FLAGS_FILE` changed.

    Parameters
    ----------
    dispatcher : numba dispatcher
        Any ``@njit(cache=True)`` function of the dependent module (locates its cache).
    module_file : str
        ``__file__`` of the dependent module.
    deps : str
        Source files whose code or constants that module's kernels compile in (none: the
        module depends on the compile flags alone).

    Returns
    -------
    bool
        True if stale entries were deleted (or no record existed yet).

    Never raises for file-system problems (a read-only cache just stays as numba left it);
    call it at import, before the first call of a kernel loads the cache.
    """
    mod = Path(module_file)
    h = hashlib.sha256()
    for dep in (str(FLAGS_FILE), *deps):
        h.update(Path(dep).read_bytes())
    stamp = h.hexdigest()
    cache_dir = _cache_dir(dispatcher, mod)
    record = cache_dir / f"{mod.stem}.deps-sha256"
    try:
        if record.read_text() == stamp:
            return False
    except OSError:
        pass
    dropped = 0
    for pattern in (f"{mod.stem}.*.nbi", f"{mod.stem}.*.nbc"):
        for f in cache_dir.glob(pattern):
            try:
                f.unlink()
                dropped += 1
            except OSError:  # another process removed it first, or a read-only cache
                pass
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        record.write_text(stamp)
    except OSError:
        return True
    if dropped:
        log.info("%s: %d numba cache files dropped (a dependency changed)", mod.name, dropped)
    return True
