"""The shared datasets folder for the benchmarks that need it: :func:`require_datasets_dir`."""

from __future__ import annotations

from pathlib import Path

from stemmap.datasets import find_datasets_dir

#: What a benchmark says (on stderr, exit status 1) when it finds no datasets folder.
MISSING = "error: ../shared/datasets not found (set STEMMAP_DATASETS)."


def require_datasets_dir(given: Path | None = None) -> Path:
    """``given`` (a script's ``--datasets``) when set, else the shared datasets folder:
    ``$STEMMAP_DATASETS``, else the nearest ``shared/datasets`` above the working directory
    or above benchmarks/ (:func:`stemmap.datasets.find_datasets_dir`). Without one the script
    stops with :data:`MISSING` (``SystemExit``: exit status 1, the message on stderr)."""
    found = given or find_datasets_dir() or find_datasets_dir(Path(__file__).resolve().parent)
    if found is None:
        raise SystemExit(MISSING)
    return found
