"""Loaders for known public datasets, each returning core types.

The data are never shipped with stemmap: point a loader at a folder, or let
:func:`find_datasets_dir` locate a ``shared/datasets`` folder beside the project.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["find_datasets_dir"]


def find_datasets_dir(start: str | os.PathLike[str] | None = None) -> Path | None:
    """The shared datasets folder: ``$STEMMAP_DATASETS`` if set, else the nearest
    ``shared/datasets`` in ``start`` (default: the working directory) or one of its parents."""
    env = os.environ.get("STEMMAP_DATASETS")
    if env:
        return Path(env)
    here = Path(start or Path.cwd()).resolve()
    for parent in [here, *here.parents]:
        cand = parent / "shared" / "datasets"
        if cand.is_dir():
            return cand
    return None
