"""The pilot region of a tile-catalog run: the statistics decided once for the whole catalog.

A catalog's chunks must run with the state one process over the whole cloud would have: the
detector's grid anchors, point spacing, noise floor, the ground / no-ground decision and its
``base_z``. :func:`catalog_statistics` measures them once on a pilot region
(:func:`pilot_chunk`: the densest box of about ``max_points`` points near the catalog's
middle) and hands them to every chunk through the config (``CatalogRun.config``); a pre-cut
slice's z range comes from the catalog header (:func:`slice_z_range`). Used by
:mod:`stemmap.engine.stems`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any

from stemmap.cloud import MunjerConfig, SensorPositions, StemConfig
from stemmap.cloud.ground import BASE_GROUND, BASE_STEM
from stemmap.engine.catalog import Catalog, Chunk
from stemmap.engine.staging import chunk_points, task_clock, task_spent

__all__ = [
    "anchored_config",
    "catalog_base",
    "catalog_corner",
    "catalog_statistics",
    "config_with_statistics",
    "log_statistics",
    "pilot_box",
    "pilot_chunk",
    "pilot_statistics",
    "slice_z_range",
]

log = logging.getLogger(__name__)


def slice_z_range(catalog: Catalog, cfg: StemConfig | MunjerConfig) -> tuple[float, float] | None:
    """The catalog's header z range for a slice catalog (``slice_mode="always"``, decided
    once for the whole catalog from its header z range by the run, :mod:`stemmap.engine.
    stems`): a pre-cut slice's sub-slices and breast height are laid out on
    its whole z extent (:func:`stemmap.cloud.stems._slice_setup`), which a chunk's points
    may not reach (a tilted slice: the stem's z, the slice's middle, would be the chunk's).
    None otherwise."""
    if isinstance(cfg, StemConfig) and cfg.slice_mode == "always":
        return catalog.z_range
    return None


def catalog_base(statistics: dict[str, Any] | None) -> tuple[str, float] | None:
    """The height reference the pilot region decided for the whole catalog (``("ground",
    nan)`` or ``("lowest stem points", z)``, :func:`stemmap.cloud.prepare_cloud`'s
    ``base``), or None (no pilot, an unreadable one, a slice catalog): each chunk decides
    on its own points."""
    what = str((statistics or {}).get("base") or "")
    if what == BASE_GROUND:
        return (BASE_GROUND, math.nan)
    z = float((statistics or {}).get("base_z") or math.nan)
    return (BASE_STEM, z) if what == BASE_STEM and math.isfinite(z) else None


def pilot_box(catalog: Catalog, max_points: int) -> tuple[float, float, float, float]:
    """The catalog's bounding box, or when it is expected to hold more than ``max_points``
    points, the largest box with the same centre and aspect expected to hold at most that
    many (header densities; independent of the chunk layout)."""
    x0, y0, x1, y1 = catalog.bounds
    cx, cy, hw, hh = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2

    def box(f: float) -> tuple[float, float, float, float]:
        return (cx - f * hw, cy - f * hh, cx + f * hw, cy + f * hh)

    if catalog.expected_points(box(1.0)) <= max_points:
        return (x0, y0, x1, y1)  # exactly: the pilot is the whole catalog
    lo, hi = 0.0, 1.0
    for _ in range(40):  # expected points grow monotonically with f
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if catalog.expected_points(box(mid)) <= max_points else (lo, mid)
    return box(lo)


def anchored_config(catalog: Catalog, config: StemConfig, *, pilot: bool = False) -> StemConfig:
    """``config`` with its ground raster spanning the catalog's header box (each chunk
    builds the part its buffer covers; without it a chunk's raster would end at its own
    points) and, unless a ``pilot`` region will measure them (:func:`pilot_statistics`), its
    grids anchored at the catalog's lower-left header corner (one anchor for every chunk;
    without it each chunk would anchor them at its own points' minimum). Values already set
    are kept."""
    x0, y0, x1, y1 = catalog.bounds
    if config.grid_origin is None and not pilot:
        config = replace(config, grid_origin=(x0, y0))
    if config.ground_extent is None:
        config = replace(config, ground_extent=(x0, y0, x1, y1))
    return config


def catalog_corner(catalog: Catalog) -> tuple[float, float]:
    """The catalog's lower-left header corner ``(x0, y0)``: the grid anchor of every chunk
    when no pilot region measured one (:func:`config_with_statistics`)."""
    return (catalog.bounds[0], catalog.bounds[1])


def pilot_chunk(catalog: Catalog, max_points: int) -> Chunk:
    """The pilot region (:func:`pilot_box`) as an unbuffered chunk named ``"pilot"`` (it is
    staged and read like a chunk)."""
    b = pilot_box(catalog, max_points)
    tiles = tuple(k for k, t in enumerate(catalog.tiles) if t.overlaps(b))
    return Chunk("pilot", b, 0.0, tiles, (True,) * 4, catalog.expected_points(b))


def pilot_statistics(
    catalog: Catalog,
    pilot: Chunk,
    config: StemConfig,
    sensor: SensorPositions | None = None,
    time_field: str | None = None,
    stage: str | None = None,
    *staged: dict[str, Any],
) -> dict[str, Any]:
    """The point spacing and slice noise floor our detector measures on the pilot region
    (:func:`stemmap.cloud.detect_statistics`: the detector's steps up to the noise floor,
    exactly; no canopy raster, no stem measurement), its height reference (``base``,
    ``base_z``: ground, or the flat base of a tree without ground) and the anchors of the
    detector's grids (``grid_origin``, ``filter_origin``).

    When the pilot region is the whole catalog (``whole``: it holds at most the point
    budget) these are a single process's over the whole cloud: the grids anchored as
    :func:`stemmap.cloud.detect_stems` anchors them (:func:`stemmap.cloud.grid_anchors`:
    the band's minimum and the filtered points'), so every chunk gets the same cells, slice
    noise floor and base as one process and finds the same stems. A pilot that is part of a
    larger catalog anchors the grids at the catalog's lower-left header corner (the band's
    minimum is not known) and decides the base on its own points. A ``config`` with a
    ``grid_origin`` keeps it.

    Runs on a worker (or in the client with ``stage=None``: a direct read). ``staged`` are
    the staging outcomes of its tiles (:func:`~stemmap.engine.staging.stage_tile_outcome`).
    Never raises: an unreadable region gives NaN values and a ``reason``. Its staged
    fragments stay (a pilot rescheduled after its worker died reads them again): the client
    removes them.
    """
    from stemmap.cloud import detect_prepared, grid_anchors, prepare_cloud
    from stemmap.engine.staging import check_staged

    c0 = task_clock()
    whole = tuple(pilot.box) == tuple(catalog.bounds)
    nan = {"spacing": math.nan, "noise_floor": math.nan, "n_points": 0, "whole": whole}
    try:
        check_staged(staged)
        fields = (time_field,) if time_field else ()
        xyz, extra = chunk_points(catalog, pilot, stage, fields)
        n = int(xyz.shape[0])
        if n == 0:
            return {**nan, "reason": "the pilot region holds no point", **task_spent(c0)}
        origins = None
        if sensor is not None:
            times = extra[time_field] if time_field else None
            origins = sensor.origins(n, times, "the pilot region")
        # the pilot's ground raster spans its own points, as before the catalog-wide
        # ground extent (a centred pilot box inside a large catalog is no chunk); the
        # steps of stemmap.cloud.detect_statistics, keeping the band for the anchors
        cfg = replace(config, ground_extent=None, estimate_height=False)
        own = config.grid_origin is None
        if own and not whole:
            cfg = replace(cfg, grid_origin=catalog_corner(catalog))
        prep = prepare_cloud(xyz, cfg, origins=origins, z_range=slice_z_range(catalog, cfg))
        st = detect_prepared(prep, cfg, statistics_only=True)
        anchors = grid_anchors(prep, cfg, float(st.spacing)) if own and whole else None
    except Exception as exc:  # an unreadable tile: its chunks fail and are reported later
        return {**nan, "reason": f"pilot region unreadable: {exc}", **task_spent(c0)}
    origin = cfg.grid_origin if anchors is None else anchors[1]
    return {
        "spacing": float(st.spacing),
        "noise_floor": float(st.noise_floor),
        "n_points": n,
        "whole": whole,
        "reason": st.reason,
        "base": st.base,
        "base_z": float(st.base_z) if math.isfinite(st.base_z) else None,
        "grid_origin": None if origin is None else list(origin),
        "filter_origin": None if anchors is None else list(anchors[0]),
        **task_spent(c0),
    }


def config_with_statistics(
    config: StemConfig, stats: dict[str, Any] | None, corner: tuple[float, float]
) -> StemConfig:
    """``config`` with the pilot's spacing and noise floor filled in where unset (a
    non-finite or non-positive value stays unset: each chunk then measures its own), and
    its grid anchors (:func:`pilot_statistics`; without them, the catalog's lower-left
    ``corner``)."""
    if config.grid_origin is None:
        got = (stats or {}).get("grid_origin")
        fo = (stats or {}).get("filter_origin")
        config = replace(
            config,
            grid_origin=corner if not got else (float(got[0]), float(got[1])),
            filter_origin=None if not (got and fo) else (float(fo[0]), float(fo[1])),
        )
    if stats is None:
        return config

    def pick(mine: float | None, value: Any) -> float | None:
        if mine is not None:
            return mine
        v = math.nan if value is None else float(value)
        return v if math.isfinite(v) and v > 0 else None

    return replace(
        config,
        spacing=pick(config.spacing, stats.get("spacing")),
        noise_floor=pick(config.noise_floor, stats.get("noise_floor")),
    )


def log_statistics(
    config: StemConfig, pilot: Chunk, stats: dict[str, Any], catalog_points: int
) -> None:
    """Log the statistics the ``pilot`` region gave the catalog (:func:`pilot_statistics`'s
    ``stats``; values set in ``config`` win): an info line with the spacing and noise floor,
    a warning when a pilot that is only part of the catalog found no ground (heights then
    from its lowest points in every chunk), and one when it measured no spacing or noise
    floor (each chunk then measures its own)."""
    sp = config.spacing if config.spacing is not None else float(stats["spacing"])
    nf = config.noise_floor if config.noise_floor is not None else float(stats["noise_floor"])
    log.info(
        "catalog statistics from %d points in (%.1f, %.1f, %.1f, %.1f): spacing %.4f m, "
        "noise floor %.4f m",
        int(stats.get("n_points", 0)),
        *pilot.box,
        sp,
        nf,
    )
    if stats.get("base") == BASE_STEM and not stats.get("whole", True):
        log.warning(
            "the pilot region (%d of the catalog's %d points) holds no ground: heights "
            "are measured from its lowest points, z = %.3f, in every chunk, as for one tree "
            "exported without ground; a single process decides that on the whole cloud.",
            int(stats.get("n_points", 0)),
            catalog_points,
            float(stats.get("base_z") or math.nan),
        )
    if not (math.isfinite(sp) and math.isfinite(nf)):
        log.warning(
            "the pilot region could not measure the catalog's point spacing / noise floor "
            "(%s); each chunk measures its own, so stems near chunk edges may differ slightly "
            "from a single-process run. Set them with StemConfig(spacing=, noise_floor=).",
            stats.get("reason") or "no plausible slice fit",
        )


def catalog_statistics(
    catalog: Catalog,
    config: StemConfig,
    *,
    max_points: int = 8_000_000,
    sensor: SensorPositions | None = None,
    time_field: str | None = None,
) -> StemConfig:
    """``config`` with the grid origin, point spacing and slice noise floor of the catalog
    filled in, computed in this process (the engine computes the same on a worker from the
    staged pilot region, :func:`pilot_statistics`).

    The detector's clustering and vertical-filter grids are anchored at
    ``StemConfig.grid_origin``, set here to the catalog's lower-left header corner (without
    it each chunk would anchor them at its own points' minimum).

    Our detector measures both on the points it is given (``StemConfig.spacing``,
    ``StemConfig.noise_floor``); measured per buffered chunk they would differ from chunk to
    chunk and from a single process over the whole cloud, and with them the clustering cell,
    the slice layout of a sparse cloud and the residual test. They are measured once, by the
    detector on a pilot region (:func:`pilot_box`: the whole catalog when it holds at most
    ``max_points`` points, else a centred box holding about that many), and every chunk gets
    them through its config. Values already set in ``config`` are kept. When the pilot
    measures nothing (no band points, no plausible slice fit) the value stays unset and each
    chunk measures its own (logged as a warning).
    """
    need = config.spacing is None or config.noise_floor is None
    config = anchored_config(catalog, config, pilot=need)
    if not need:
        return config
    pilot = pilot_chunk(catalog, max_points)
    stats = pilot_statistics(catalog, pilot, config, sensor, time_field, None)
    log_statistics(config, pilot, stats, catalog.n_points)
    return config_with_statistics(config, stats, catalog_corner(catalog))
