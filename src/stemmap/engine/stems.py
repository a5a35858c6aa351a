"""Stems over a tile catalog: one Dask task per buffered chunk, merged once all are done.

Each task (:func:`stems_chunk`) reads its buffered chunk (:func:`~stemmap.engine.catalog.
read_chunk`), runs the public detector (:func:`stemmap.cloud.detect_stems`: ground model and
stems of the buffered points), keeps the stems whose centre the chunk owns
(:meth:`~stemmap.engine.catalog.Chunk.owns`) and writes them atomically to the run's work
folder. The client appends a manifest line per chunk (:class:`~stemmap.engine.manifest.
Manifest`), skips chunks already done on ``resume``, and merges the chunk results into one
:class:`~stemmap.cloud.CloudStems` sorted by x then y.

Equivalence with one process over the whole cloud holds when the buffer covers what the
detector looks at around a stem: its points (half a DBH), its cluster, and the ground raster
cells under it with their 3 x 3 neighbourhoods (two ground cells, plus one for the raster's
bilinear interpolation) -- :data:`MIN_EXACT_BUFFER` with the default 1 m ground cell. The
cloud's slice mode (a pre-cut slice or a full cloud) is decided once for the whole catalog from
the header z range, never per chunk; the detector's grid origin, point spacing and noise floor
once by :func:`catalog_statistics`, so each chunk runs with the single process's state
(``CatalogRun.config``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.cloud import CloudStems, MunjerConfig, SensorPositions, StemConfig
from stemmap.cloud.ground import BASE_STEM
from stemmap.cloud.stems import STEM_BASE_NOTE
from stemmap.engine.catalog import Catalog, Chunk, plan_chunks
from stemmap.engine.cluster import Dep, TaskOutcome, dask_client, run_graph
from stemmap.engine.manifest import (
    Manifest,
    load_columns,
    params_hash,
    result_hash,
    save_columns,
)
from stemmap.engine.pilot import (
    anchored_config,
    catalog_base,
    catalog_corner,
    catalog_statistics,
    config_with_statistics,
    log_statistics,
    pilot_chunk,
    pilot_statistics,
    slice_z_range,
)
from stemmap.engine.staging import (
    chunk_points,
    clear_stage,
    stage_tile_outcome,
    task_clock,
    task_spent,
)
from stemmap.errors import InputError, StemmapError

__all__ = [
    "DEFAULT_BUFFER",
    "MIN_EXACT_BUFFER",
    "PREPARE_APART_FRACTION",
    "CatalogRun",
    "catalog_statistics",
    "merge_chunk_results",
    "pilot_chunk",
    "pilot_statistics",
    "prepare_chunk",
    "run_stems_catalog",
    "stems_chunk",
]

log = logging.getLogger(__name__)

#: Default buffer, metres: above :data:`MIN_EXACT_BUFFER` with a margin.
DEFAULT_BUFFER = 5.0
#: Smallest buffer (m) for which chunked results equal one process over the whole cloud with
#: the default detector: max DBH / 2 (0.75 m) + 3 ground cells of 1 m.
MIN_EXACT_BUFFER = 3.75

#: The chunks' ground step (:func:`prepare_chunk`) runs as tasks of its own, while the pilot
#: region measures the catalog statistics, only when the pilot holds more than this fraction
#: of the catalog's points (expected from the headers). Otherwise each chunk is one task
#: (read, ground, stems; it waits for the pilot): with a small pilot the other workers
#: still have tiles to stage while it runs -- the pilot costs ~0.4 CPU-s per million
#: points, staging ~0.22 --, and the split's cost is gone: a second task per chunk and the
#: slice band written to and read back from the stage (101 M points, 20 m chunks: 451 ->
#: 251 tasks; docs/algorithms/engine.md, "Seventh pass"). With a pilot covering most of the
#: catalog (up to 8 M points) the split lets chunks be prepared while it runs.
PREPARE_APART_FRACTION = 0.25

#: the scalar (per-cloud) fields of a CloudStems; every other field is a per-stem column
_SCALARS = ("method", "frame", "spacing", "reason", "base", "noise_floor", "base_z")
#: the per-stem (array) columns of a CloudStems, as stored in a chunk result
_COLUMNS = tuple(f.name for f in fields(CloudStems) if f.name not in _SCALARS)


def _storable(v: Any) -> Any:
    """An array savable without pickle: object (string) columns become unicode arrays."""
    a = np.asarray(v)
    return a.astype(str) if a.dtype == object else a


def _detect(
    xyz: np.ndarray,
    cfg: StemConfig | MunjerConfig,
    origins: np.ndarray | None,
    chunk: Chunk,
    base: tuple[str, float] | None = None,
    z_range: tuple[float, float] | None = None,
) -> CloudStems:
    """The detector on a buffered chunk; ours fits only the clusters near the owned area
    (``detect_prepared(region=)``: the owned stems are the same), with the catalog's height
    reference ``base`` (:func:`catalog_base`; None: decided on the chunk's points) and, for
    a slice catalog, its z range (:func:`slice_z_range`)."""
    from stemmap.cloud import detect_prepared, detect_stems_munjer, prepare_cloud

    if isinstance(cfg, MunjerConfig):
        return detect_stems_munjer(xyz, cfg)
    prep = prepare_cloud(
        xyz, cfg, origins=origins, ground_window=chunk.buffered, base=base, z_range=z_range
    )
    return detect_prepared(prep, cfg, region=chunk.owned_region)


_NO_POINTS = "the buffered chunk holds no point"


def _no_points(method: str) -> CloudStems:
    return CloudStems.empty(method, reason=_NO_POINTS)


def _chunk_stems(
    catalog: Catalog,
    chunk: Chunk,
    config: StemConfig | MunjerConfig,
    sensor: SensorPositions | None,
    time_field: str | None,
    stage: str | None,
    base: tuple[str, float] | None = None,
) -> tuple[CloudStems, int]:
    """All stems the detector finds in the buffered chunk (owned or not), and its points."""
    fields = (time_field,) if time_field else ()
    xyz, extra = chunk_points(catalog, chunk, stage, fields)
    n = int(xyz.shape[0])
    if n == 0:
        return _no_points("munjer2025" if isinstance(config, MunjerConfig) else "ours"), 0
    origins = None
    if sensor is not None:
        times = extra[time_field] if time_field else None
        origins = sensor.origins(n, times, f"chunk {chunk.id}")
    return _detect(xyz, config, origins, chunk, base, slice_z_range(catalog, config)), n


def _prepared_path(stage: str, chunk_id: str) -> Path:
    return Path(stage) / chunk_id / "prepared.npz"


def prepare_chunk(
    catalog: Catalog,
    chunk: Chunk,
    config: StemConfig,
    stage: str,
    sensor: SensorPositions | None = None,
    time_field: str | None = None,
    *staged: dict[str, Any],
) -> dict[str, Any]:
    """The detector's ground step on one buffered chunk (:func:`stemmap.cloud.prepare_cloud`:
    ground raster, heights, slice band, canopy raster), saved beside its fragments.

    Runs on a worker, before the catalog statistics are known (the ground step does not use
    them), so chunks are prepared while the pilot region is measured. ``staged``: the
    staging outcomes of its tiles (an unreadable tile fails the chunk with its error).
    Returns the points read, the saved file and the seconds spent.
    """
    from stemmap.cloud import PreparedCloud, prepare_cloud
    from stemmap.engine.staging import check_staged

    c0 = task_clock()
    check_staged(staged)
    fields = (time_field,) if time_field else ()
    xyz, extra = chunk_points(catalog, chunk, stage, fields)
    n = int(xyz.shape[0])
    origins = None
    if sensor is not None and n:
        times = extra[time_field] if time_field else None
        origins = sensor.origins(n, times, f"chunk {chunk.id}")
    prep = (
        prepare_cloud(
            xyz,
            config,
            origins=origins,
            ground_window=chunk.buffered,
            z_range=slice_z_range(catalog, config),
        )
        if n
        else PreparedCloud(None)
    )
    path = _prepared_path(stage, chunk.id)
    save_columns(path, prep.to_columns(), durable=False)  # scratch: read by stems_chunk
    return {"n_points": n, "path": str(path), **task_spent(c0)}


def stems_chunk(
    catalog: Catalog,
    chunk: Chunk,
    config: StemConfig | MunjerConfig,
    result_path: str,
    sensor: SensorPositions | None = None,
    time_field: str | None = None,
    stage: str | None = None,
    statistics: dict[str, Any] | None = None,
    prepared: dict[str, Any] | None = None,
    *staged: dict[str, Any],
) -> dict[str, Any]:
    """Detect stems in one buffered chunk and write the owned ones to ``result_path`` (.npz).

    Runs on a worker. The points come from the staged fragments of its LAS/LAZ tiles
    (``stage``, :mod:`~stemmap.engine.staging`; ``staged``: their staging outcomes, an
    unreadable tile fails the chunk with its error) or are read directly (COPC tiles, or
    ``stage=None``); or the chunk was prepared before (``prepared``: the result of
    :func:`prepare_chunk`) and only the steps after the ground run here.
    ``statistics``: the pilot region's spacing and noise floor (:func:`pilot_statistics`),
    filled into ``config`` where unset. Returns a small summary (points read, stems kept,
    seconds -- with the preparation's --, the statistics used).
    """
    from stemmap.cloud import PreparedCloud, detect_prepared
    from stemmap.engine.staging import check_staged

    c0 = task_clock()
    check_staged(staged)
    base = None
    if isinstance(config, StemConfig):
        config = config_with_statistics(config, statistics, catalog_corner(catalog))
        base = catalog_base(statistics)
    before = 0.0  # the preparation's seconds (the manifest records the chunk's total)
    prep = None
    if prepared is not None and isinstance(config, StemConfig):
        prep = PreparedCloud.from_columns(load_columns(Path(prepared["path"])))
        before = float(prepared["task_s"])
        if not _same_base(prep, base):  # prepared before the pilot decided: again
            prep = None
    if prep is not None and prepared is not None and isinstance(config, StemConfig):
        n = int(prepared["n_points"])
        stems = (
            detect_prepared(prep, config, region=chunk.owned_region) if n else _no_points("ours")
        )
    else:
        stems, n = _chunk_stems(catalog, chunk, config, sensor, time_field, stage, base)
    method = "munjer2025" if isinstance(config, MunjerConfig) else "ours"
    own = stems.select(np.flatnonzero(chunk.owns(stems.xy))) if len(stems) else stems
    cols: dict[str, Any] = {k: _storable(getattr(own, k)) for k in _COLUMNS}
    cols["method"] = np.array(own.method or method)
    cols["spacing"] = np.array(own.spacing)
    cols["noise_floor"] = np.array(own.noise_floor)
    cols["base"] = np.array(getattr(own, "base", ""))
    cols["base_z"] = np.array(float(getattr(own, "base_z", math.nan)))
    cols["reason"] = np.array(str(stems.reason or ""))  # why the chunk found none
    # not fsynced: the manifest line records its hash and a resume checks it
    save_columns(Path(result_path), cols, durable=False)
    return {
        "n_points": n,
        "n_stems": len(own),
        "result": result_hash(result_path),
        "n_found": len(stems),
        "seconds": before + time.perf_counter() - c0[0],
        "spacing": getattr(config, "spacing", None),
        "noise_floor": getattr(config, "noise_floor", None),
        "grid_origin": _listed(getattr(config, "grid_origin", None)),
        "filter_origin": _listed(getattr(config, "filter_origin", None)),
        "base": getattr(stems, "base", ""),
        "base_z": _finite(getattr(stems, "base_z", math.nan)),
        **task_spent(c0),
    }


def _listed(v: Any) -> list[float] | None:
    return None if v is None else [float(x) for x in v]


def _finite(v: Any) -> float | None:
    return float(v) if v is not None and math.isfinite(float(v)) else None


def _same_base(prep: Any, base: tuple[str, float] | None) -> bool:
    """Whether a chunk prepared on its own points (:func:`prepare_chunk`, before the pilot
    decided the catalog's base) measured its heights from the catalog's ``base``."""
    band = prep.band
    if base is None or band is None:
        return True
    if band.base != base[0]:
        return False
    return base[0] != BASE_STEM or band.base_z == base[1]


def merge_chunk_results(paths: list[Path], method: str = "ours") -> CloudStems:
    """Concatenate chunk results into one CloudStems sorted by x, then y (independent of the
    chunking)."""
    loaded = [load_columns(p) for p in paths]
    # the height reference: every chunk's, those without stems too (the catalog's base is
    # one decision, catalog_base; a flat base's z is stated when all chunks share it)
    bases = sorted({str(p["base"]) for p in loaded if "base" in p} - {""})
    zs = {float(p["base_z"]) for p in loaded if "base_z" in p and str(p["base"]) == BASE_STEM}
    base_z = zs.pop() if bases == [BASE_STEM] and len(zs) == 1 else math.nan
    parts = [p for p in loaded if np.asarray(p["xy"]).size]
    if not parts:  # why: the chunks' own reasons (a chunk without points says so too)
        why = sorted(
            {str(p["reason"]).replace(STEM_BASE_NOTE, "") for p in loaded if "reason" in p}
        )
        why = [w for w in why if w and w != _NO_POINTS]
        reason = "no chunk found a stem" + (f" ({'; '.join(why)})" if why else "")
        if bases == [BASE_STEM]:
            reason += STEM_BASE_NOTE
        empty = CloudStems.empty(method, reason=reason)
        return replace(empty, base=", ".join(bases), base_z=base_z)
    cols = {k: np.concatenate([np.asarray(p[k]) for p in parts if k in p]) for k in _COLUMNS}
    xy = cols["xy"].reshape(-1, 2)
    order = np.lexsort((xy[:, 1], xy[:, 0]))
    merged = {k: v[order] for k, v in cols.items()}
    sp = [float(p["spacing"]) for p in parts if math.isfinite(float(p["spacing"]))]
    nf = [float(p.get("noise_floor", math.nan)) for p in parts]
    nf = [v for v in nf if math.isfinite(v)]
    return CloudStems.from_columns(
        **merged,
        base=", ".join(bases),
        base_z=base_z,
        method=str(parts[0]["method"]),
        frame="cloud",
        spacing=float(np.median(sp)) if sp else math.nan,
        noise_floor=float(np.median(nf)) if nf else math.nan,
    )


@dataclass
class CatalogRun:
    """Outcome of :func:`run_stems_catalog`.

    ``stems`` is None when a chunk failed (no merged product is written then); ``failed``
    maps chunk id -> error; ``skipped`` lists the chunks a resume found done.
    """

    stems: CloudStems | None
    chunks: list[Chunk]
    computed: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    n_points: int = 0
    work: Path = Path()
    #: the configuration every chunk ran with (slice mode, spacing and noise floor of the
    #: catalog filled in): ``detect_stems(cloud, run.config)`` is the single-process equivalent
    config: StemConfig | MunjerConfig | None = None
    #: per phase (``stage``, ``pilot``, ``prepare``, ``stems``): tasks run, and the wall and
    #: CPU seconds they spent on the workers (summed) -- where a run's time goes
    phases: dict[str, dict[str, float]] = field(default_factory=dict)


def _catalog_config(catalog: Catalog, cfg: StemConfig | MunjerConfig) -> StemConfig | MunjerConfig:
    """Decide the slice mode once from the catalog's header z range (a single process decides
    it from the whole cloud; a chunk holding only flat ground must not pass for a slice)."""
    if not isinstance(cfg, StemConfig) or cfg.slice_mode != "auto":
        return cfg
    zs = np.array([(t.bounds[2], t.bounds[5]) for t in catalog.tiles])
    is_slice = float(zs[:, 1].max() - zs[:, 0].min()) < 1.0
    return replace(cfg, slice_mode="always" if is_slice else "never")


def run_stems_catalog(
    catalog: Catalog,
    config: StemConfig | MunjerConfig,
    work: str | Path,
    *,
    chunk_size: float | None = None,
    buffer: float = DEFAULT_BUFFER,
    max_points: int = 8_000_000,
    workers: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    retries: int = 2,
    sensor: SensorPositions | None = None,
    on_progress: Callable[[str, int, int], None] | None = None,
    client: Any = None,
) -> CatalogRun:
    """Detect stems over a tile catalog on Dask, chunk by chunk, resumable.

    Parameters
    ----------
    catalog : Catalog
    config : StemConfig or MunjerConfig
    work : path
        Work folder (manifest + per-chunk results); created if missing.
    chunk_size, buffer, max_points
        Chunk layout (:func:`~stemmap.engine.catalog.plan_chunks`), metres / points.
    workers, scheduler
        Local cluster size or a running scheduler's address
        (:func:`~stemmap.engine.cluster.dask_client`); ignored when ``client`` is given.
    resume : bool
        Skip chunks the manifest records as done with the same input hashes and parameters.
        Without it, the manifest is restarted.
    retries : int
        Extra attempts of a failing chunk before it is reported failed.
    sensor : SensorPositions, optional
        Sensor positions for the along-ray fits (ours); a trajectory reads each point's time.
    on_progress : callable(phase, done, total), optional
        Called in the client as tiles are read (phase ``"reading tiles"``) and chunks finish
        (``"chunks"``; chunks a resume skips count as done from the start).

    Returns
    -------
    CatalogRun
    """
    cfg = _catalog_config(catalog, config)
    if buffer < MIN_EXACT_BUFFER:
        log.warning(
            "buffer %.2f m < %.2f m: stems near chunk edges may differ from a single-process "
            "run (ground and stem fits see less than they would)",
            buffer,
            MIN_EXACT_BUFFER,
        )
    chunks = plan_chunks(catalog, chunk_size, buffer, max_points=max_points)
    man = Manifest(work)
    man.claim()
    time_field: str | None = None
    if sensor is not None and sensor.needs_time:
        import laspy

        with laspy.open(catalog.tiles[0].path) as rd:
            names = tuple(rd.header.point_format.dimension_names)
        time_field = sensor.pick_time_field(names, repr(catalog.tiles[0].path))
    pilot: Chunk | None = None
    if isinstance(cfg, StemConfig):
        need = cfg.spacing is None or cfg.noise_floor is None
        cfg = anchored_config(catalog, cfg, pilot=need)
        if need:
            pilot = pilot_chunk(catalog, max_points)
    hashes: dict[int, str] = {}

    def inputs_of(ch: Chunk) -> dict[str, str]:
        for k in ch.tiles:
            if k not in hashes:
                hashes[k] = catalog.tiles[k].content_hash()
        return {catalog.tiles[k].path: hashes[k] for k in ch.tiles}

    # the catalog statistics are a function of the configuration and the pilot region's
    # files: both identify a chunk's parameters (the statistics are measured after this)
    base = params_hash(
        {
            "config": cfg,
            "sensor": sensor,
            "time_field": time_field,
            "pilot": None if pilot is None else [pilot.box, inputs_of(pilot)],
            # tiles not in metres (--units): the same files give other points
            **({"unit_scale": catalog.unit_scale} if catalog.unit_scale != 1.0 else {}),
        }
    )
    wanted = {
        ch.id: (inputs_of(ch), params_hash([base, ch.box, ch.buffer, ch.open_sides]))
        for ch in chunks
    }
    if resume:
        done = man.done_set(wanted)
    else:
        man.reset()
        done = set()
    todo = [ch for ch in chunks if ch.id not in done]
    run = CatalogRun(None, chunks, skipped=sorted(done), work=Path(work), config=cfg)
    log.info(
        "%d tiles, %d points, %d chunks (%d done before), buffer %.1f m",
        len(catalog),
        catalog.n_points,
        len(chunks),
        len(done),
        buffer,
    )
    if isinstance(cfg, StemConfig) and pilot is not None and not todo and chunks:
        # every chunk done before: the statistics they ran with
        run.config = config_with_statistics(
            cfg, man.entries()[chunks[0].id], catalog_corner(catalog)
        )
    stage = str(Path(work) / "stage")
    fields = (time_field,) if time_field else ()
    # one graph: stage 1 decodes each LAS/LAZ tile once into the fragments of the chunks still
    # to do; the pilot measures the catalog statistics on a worker; each chunk is one task
    # once its tiles are staged and the pilot is done -- or, when the pilot is a large part
    # of the catalog (PREPARE_APART_FRACTION), two: its ground step (prepare) as soon as its
    # tiles are staged, the rest of the detector once the pilot is done too. The pilot
    # reads staged fragments like a chunk (its tiles are decoded once, by the stage tasks);
    # its stage tasks run first among ready tasks, so with several workers it starts after
    # a few tiles' decoding and costs no second decode (reading its tiles itself cost
    # 1.6 CPU-s more at 101 M points; docs/algorithms/engine.md).
    per_tile: dict[int, list[Chunk]] = {}
    first: dict[str, int] = {}

    def build() -> list[tuple[str, Callable[..., Any], tuple[Any, ...]]]:
        per_tile.clear()
        first.clear()
        readers = [*todo, *([pilot] if pilot is not None and todo else [])]
        for ch in readers:
            for k in ch.tiles:
                if not catalog.tiles[k].copc:
                    per_tile.setdefault(k, []).append(ch)
        graph: list[tuple[str, Callable[..., Any], tuple[Any, ...]]] = [
            (f"stage-tile-{k}", stage_tile_outcome, (catalog, k, chs, stage, fields, retries))
            for k, chs in sorted(per_tile.items())
        ]

        def deps(ch: Chunk) -> list[Dep]:
            return [Dep(f"stage-tile-{k}") for k in ch.tiles if k in per_tile]

        stats: Any = None
        apart = False
        if pilot is not None and todo:
            apart = pilot.expected_points > PREPARE_APART_FRACTION * catalog.n_points
            pilot_args = (catalog, pilot, cfg, sensor, time_field, stage, *deps(pilot))
            graph.append(("pilot", pilot_statistics, pilot_args))
            stats = Dep("pilot")
            # every chunk's second step waits for the pilot: it and its tiles go first
            first.update({d.key: 1 for d in deps(pilot)}, pilot=2)
        for ch in todo:
            path = str(man.result_path(ch.id))
            args: tuple[Any, ...] = (catalog, ch, cfg, path, sensor, time_field, stage, stats)
            if not apart:  # one task: read, ground and stems (after the pilot, if any)
                args += (None, *deps(ch))
            else:  # the ground step runs while the pilot is measured; the rest after it
                prep = (catalog, ch, cfg, stage, sensor, time_field, *deps(ch))
                graph.append((f"prepare-chunk-{ch.id}", prepare_chunk, prep))
                args += (Dep(f"prepare-chunk-{ch.id}"),)
            graph.append((f"stems-chunk-{ch.id}", stems_chunk, args))
        return graph

    n_stage = 0
    staged = 0
    count = len(done)

    def task_done(oc: TaskOutcome) -> None:
        nonlocal staged, count
        if oc.ok and isinstance(oc.value, dict) and "cpu_s" in oc.value:
            phase = oc.key.split("-")[0]
            acc = run.phases.setdefault(phase, {"tasks": 0, "task_s": 0.0, "cpu_s": 0.0})
            acc["tasks"] += 1
            acc["task_s"] += float(oc.value["task_s"])
            acc["cpu_s"] += float(oc.value["cpu_s"])
        if oc.key.startswith("stage-tile-"):
            staged += 1
            if on_progress is not None:
                on_progress("reading tiles", staged, n_stage)
            return
        if oc.key == "pilot":
            assert pilot is not None and isinstance(cfg, StemConfig)
            value = oc.value if oc.ok else {"spacing": math.nan, "noise_floor": math.nan}
            log_statistics(cfg, pilot, {"reason": oc.error, **value}, catalog.n_points)
            run.config = config_with_statistics(cfg, value, catalog_corner(catalog))
            clear_stage(stage, pilot.id)
            return
        if oc.key.startswith("prepare-chunk-"):
            return  # its outcome reaches the chunk's stems task (an error fails it)
        cid = oc.key.removeprefix("stems-chunk-")
        inputs, params = wanted[cid]
        if oc.ok:
            man.append(
                cid,
                "done",
                inputs,
                params,
                seconds=oc.value["seconds"],
                n_points=oc.value["n_points"],
                n_stems=oc.value["n_stems"],
                spacing=oc.value["spacing"],
                noise_floor=oc.value["noise_floor"],
                grid_origin=oc.value.get("grid_origin"),
                filter_origin=oc.value.get("filter_origin"),
                base=oc.value.get("base"),
                base_z=oc.value.get("base_z"),
                result=oc.value["result"],
            )
            run.computed.append(cid)
            run.n_points += int(oc.value["n_points"])
            clear_stage(stage, cid)
        else:
            man.append(cid, "failed", inputs, params, error=oc.error)
            run.failed[cid] = oc.error
        count += 1
        if on_progress is not None:
            on_progress("chunks", count, len(chunks))

    man.chunks.mkdir(parents=True, exist_ok=True)

    def execute(cl: Any) -> None:
        nonlocal n_stage
        graph = build()
        n_stage = len(per_tile)
        if on_progress is not None:
            on_progress("reading tiles", 0, n_stage)
            on_progress("chunks", len(done), len(chunks))
        run_graph(cl, graph, retries=retries, priorities=first, on_done=task_done)

    if not todo and on_progress is not None:
        on_progress("chunks", len(done), len(chunks))
    if todo:
        if client is not None:
            execute(client)
        else:
            with dask_client(workers, scheduler) as cl:
                execute(cl)
    if run.failed:
        return run
    clear_stage(stage)
    method = "munjer2025" if isinstance(cfg, MunjerConfig) else "ours"
    try:
        run.stems = merge_chunk_results([man.result_path(ch.id) for ch in chunks], method)
    except StemmapError:
        raise
    except Exception as exc:  # pragma: no cover - a result file removed under our feet
        raise InputError(f"merging the chunk results in {work} failed: {exc}") from exc
    return run
