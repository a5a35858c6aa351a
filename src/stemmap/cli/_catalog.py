"""``stemmap stems`` over a tile catalog: the CLI side of :mod:`stemmap.engine`.

When the engine kicks in (:func:`wants_engine`): several inputs, a folder of LAS/LAZ tiles, a
glob, a list file, or any engine option (``--chunk-size``, ``--buffer``, ``--workers``,
``--scheduler``, ``--resume``). A single file without them runs in this process as before
(streamed in two passes, no cluster started).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from stemmap.cli._common import console, progress
from stemmap.engine.logs import is_ros2_bag
from stemmap.errors import ConfigError

if TYPE_CHECKING:
    from stemmap.cloud import CloudStems, MunjerConfig, SensorPositions, StemConfig

__all__ = ["EngineOptions", "is_ros2_bag", "run_catalog_stems", "wants_engine"]


@dataclass(frozen=True)
class EngineOptions:
    """The engine options of ``stemmap stems`` (None / False: not given)."""

    chunk_size: float | None = None
    buffer: float | None = None
    workers: int | None = None
    scheduler: str | None = None
    resume: bool = False
    work: Path | None = None

    @property
    def given(self) -> bool:
        return (
            self.chunk_size is not None
            or self.buffer is not None
            or self.workers is not None
            or self.scheduler is not None
            or self.resume
            or self.work is not None
        )


def wants_engine(
    inputs: Sequence[str | Path], opts: EngineOptions, extensions: Sequence[str] = (".las", ".laz")
) -> bool:
    """Whether ``stemmap stems INPUTS`` runs on the engine (see the module docstring); with
    ``extensions`` of drive logs, whether ``stemmap detect`` / ``map`` take several logs (a
    list file is a ``.txt`` / ``.lst`` whose first entry has one of ``extensions``)."""
    if len(inputs) != 1 or opts.given:
        return True
    p = Path(inputs[0])
    if p.is_dir():
        return not is_ros2_bag(p)
    if p.is_file():
        return p.suffix.lower() in (".txt", ".lst") and _is_list_file(p, extensions)
    return any(c in str(inputs[0]) for c in "*?[")


def _is_list_file(p: Path, extensions: Sequence[str]) -> bool:
    """A .txt that names files with ``extensions`` (an XYZ text cloud starts with numbers)."""
    try:
        with p.open(encoding="utf-8") as fh:
            for line in fh:
                s = line.strip()
                if s and not s.startswith("#"):
                    return s.lower().endswith(tuple(extensions))
    except (OSError, UnicodeDecodeError):
        return False
    return False


def run_catalog_stems(
    inputs: list[str],
    cfg: StemConfig | MunjerConfig,
    opts: EngineOptions,
    sensor: SensorPositions | None,
    out_csv: Path,
    *,
    quiet: bool = False,
    unit_scale: float = 1.0,
) -> tuple[CloudStems, int, Any]:
    """Run the engine with a progress bar and a chunk count (neither when ``quiet``); exit 1
    listing the failed chunks if any failed.

    ``unit_scale``: metres per unit of the tiles' coordinates (``--units``).
    Returns the merged stems, the number of tiles and the catalog.
    """
    from stemmap.engine import DEFAULT_BUFFER, Catalog, run_stems_catalog

    if opts.workers is not None and opts.scheduler is not None:
        raise ConfigError("give --workers (a local cluster) or --scheduler, not both.")
    catalog = Catalog.from_inputs(inputs, unit_scale)
    work = opts.work or out_csv.with_name(out_csv.stem + "_chunks")
    with progress(not quiet) as bar:
        tasks: dict[str, Any] = {}

        def tick(phase: str, done: int, total: int) -> None:
            if phase not in tasks:
                tasks[phase] = bar.add_task(phase, total=total)
            bar.update(tasks[phase], completed=done, total=total)

        run = run_stems_catalog(
            catalog,
            cfg,
            work,
            chunk_size=opts.chunk_size,
            buffer=DEFAULT_BUFFER if opts.buffer is None else opts.buffer,
            workers=opts.workers,
            scheduler=opts.scheduler,
            resume=opts.resume,
            sensor=sensor,
            on_progress=tick,
        )
    if not quiet or run.failed:
        console.print(
            f"{len(catalog)} tiles, {len(run.chunks)} chunks: {len(run.computed)} computed, "
            f"{len(run.skipped)} already done, {len(run.failed)} failed (work folder {work})"
        )
    if run.failed or run.stems is None:
        for cid, err in sorted(run.failed.items()):
            console.print(f"[red]error:[/red] chunk {cid}: {err}")
        console.print(
            f"[red]error:[/red] {len(run.failed)} chunk(s) failed; {out_csv} not written. Fix "
            "the cause and rerun with --resume to redo only those chunks."
        )
        raise typer.Exit(code=1)
    return run.stems, len(catalog), catalog


def catalog_sample(catalog: Any, n: int = 200_000) -> Any:
    """Every k-th point (about ``n``; xyz, metres) of the catalog's tiles, one streaming pass:
    a PNG background (its xy) and the shape check of a run with few or no stems
    (:func:`stemmap.io.conventions.up_axis_hint`)."""
    import numpy as np

    from stemmap.io.clouds import iter_las_chunks

    k = max(1, catalog.n_points // n)
    u = catalog.unit_scale
    parts = [c.xyz[::k] * u for t in catalog.tiles for c in iter_las_chunks(t.path, 1_000_000)]
    return np.concatenate(parts) if parts else np.zeros((0, 3))


#: Added to a shape warning of a tile catalog: --up-axis applies to one file only.
CATALOG_UP_AXIS_NOTE = (
    " A tile catalog takes no --up-axis (tiles are cut on their x, y): turn the tiles z up "
    "first (PDAL filters.transformation), or run each file on its own with --up-axis."
)
