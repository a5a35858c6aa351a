"""Stem positions and diameters (DBH) from 3D point clouds.

Two methods, both returning a columnar :class:`CloudStems`:

* :func:`detect_stems_munjer` -- EB-LiDAR (Munjer et al. 2025, §3.2-3.3, Table 1): pass-through
  box, voxel-grid averaging, DBSCAN, PCA eccentricity filter, circle fit of the cluster's
  horizontal projection; :func:`associate_proximity` merges detections across frames (1.0 m).
  Preset ``"munjer2025"``.
* :func:`detect_stems` -- ours, for terrestrial, mobile and robot clouds: ground model and height
  normalisation, several horizontal slices around breast height, grid clustering of the
  slice band, robust geometric circle fits per slice (``scan.circle`` "ours", batched) with
  quality tests (arc coverage, residual, point count), a taper/lean line through the slices
  evaluated at 1.3 m, and optional stem height. Every threshold derives from the measured point
  spacing or the measured residual noise floor: no per-cloud tuning. Preset ``"ours"``.
  Clusters with too few points per slice get one pooled tilted-cylinder fit over the band
  (:func:`~stemmap.cloud.pooled._pooled_stems`); given each point's sensor position
  (``origins``), slice fits are refined with residuals along the rays
  (:func:`~stemmap.cloud.slicefit._refine_along_rays`).

:func:`detect_stems_file` streams a LAS/LAZ file in chunks (two passes: ground, then band), so
a 20-million-point cloud is processed in bounded memory; with
:class:`stemmap.cloud.sensor.SensorPositions` (a station, or a trajectory and the points' time
stamps) it gets the along-ray refinement too.

The pieces live in :mod:`~stemmap.cloud.result` (CloudStems), :mod:`~stemmap.cloud.config`
(StemConfig), :mod:`~stemmap.cloud.munjer`, :mod:`~stemmap.cloud.slicefit` (circle fits of
slices) and :mod:`~stemmap.cloud.measure` (per-stem measurement, with its steps in
:mod:`~stemmap.cloud.band`, :mod:`~stemmap.cloud.slicestem`, :mod:`~stemmap.cloud.uncertainty`,
:mod:`~stemmap.cloud.pooled` and :mod:`~stemmap.cloud.heights`); this module orchestrates them
and re-exports the public names.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from stemmap.cloud.axisfit import _reach_range, _split_reach
from stemmap.cloud.band import _Band, _grid_anchors
from stemmap.cloud.config import StemConfig
from stemmap.cloud.filters import as_xyz
from stemmap.cloud.ground import BASE_GROUND, BASE_STEM, GroundAccumulator, GroundModel
from stemmap.cloud.heights import _canopy_update
from stemmap.cloud.measure import _stems_from_band
from stemmap.cloud.munjer import MunjerConfig, associate_proximity, detect_stems_munjer
from stemmap.cloud.quantisation import naming_the_source
from stemmap.cloud.result import BASE_SLICE, BREAST_HEIGHT, CloudStems
from stemmap.cloud.sensor import SensorPositions
from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.io.conventions import CloudConvention

__all__ = [
    "BREAST_HEIGHT",
    "PRESETS",
    "CloudStems",
    "MunjerConfig",
    "PreparedCloud",
    "StemConfig",
    "associate_proximity",
    "detect_prepared",
    "detect_statistics",
    "detect_stems",
    "detect_stems_file",
    "detect_stems_munjer",
    "get_preset",
    "grid_anchors",
    "prepare_cloud",
]

log = logging.getLogger(__name__)


PRESETS: dict[str, MunjerConfig | StemConfig] = {
    "munjer2025": MunjerConfig(),
    "ours": StemConfig(),
    "ours_kasa": StemConfig(fit_method="kasa"),
}


def get_preset(name: str) -> MunjerConfig | StemConfig:
    """A named configuration (``"munjer2025"``, ``"ours"``, ``"ours_kasa"``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(
            f"unknown stems preset {name!r}; choose one of {sorted(PRESETS)}."
        ) from None


def _slice_setup(cfg: StemConfig, zmin: float, zmax: float, slice_mode: bool) -> StemConfig:
    if not slice_mode:
        return cfg
    # a pre-cut slice: split its extent into sub-slices of >= 5 cm, at most 3
    ext = max(zmax - zmin, 1e-3)
    n = int(np.clip(ext // 0.05, 1, 3))
    th = ext / n
    centers = tuple(float(zmin + th * (k + 0.5)) for k in range(n))
    return replace(
        cfg,
        slice_centers=centers,
        slice_thickness=th * 1.0001,
        min_slices=1,
        breast_height=float((zmin + zmax) / 2),
    )


def detect_stems(
    xyz: ArrayLike,
    config: StemConfig | None = None,
    *,
    ground: GroundModel | None = None,
    origins: ArrayLike | None = None,
) -> CloudStems:
    """Our stem detector on an in-memory cloud (see the module docstring).

    Parameters
    ----------
    xyz : array_like (N, 3), metres
        Any frame with z up. Clouds whose z extent is below 1 m are taken as already
        height-normalised slices (``config.slice_mode``).
    config : StemConfig, default preset "ours"
    ground : GroundModel, optional
        Use this ground instead of fitting one.
    origins : array_like (N, 3) or (3,), metres, optional
        Sensor position of each point (a TLS station; for a mobile cloud the trajectory pose
        at the point's time). When given, the slice fits are refined with residuals along the
        rays (:func:`_refine_along_rays`): range noise lies along the ray, not across the
        surface, which biases orthogonal-distance fits of one-sided arcs low. Only the
        geometric fit uses them: with ``fit_method="kasa"`` they raise a ConfigError rather
        than being silently ignored.

    Returns
    -------
    CloudStems
        ``z`` is the absolute z of breast height at each stem; ``quality`` combines the
        fraction of slices passing, their arc coverage and residual.
    """
    cfg = config or StemConfig()
    return detect_prepared(prepare_cloud(xyz, cfg, ground=ground, origins=origins), cfg)


def detect_statistics(
    xyz: ArrayLike, config: StemConfig | None = None, *, origins: ArrayLike | None = None
) -> CloudStems:
    """The point spacing and slice noise floor :func:`detect_stems` measures on this cloud,
    without measuring stems.

    The detector's steps up to the noise floor (ground, height band, spacing, clustering,
    slice fits and their quality tests) are run exactly as in :func:`detect_stems`; the
    canopy raster (stem heights) and everything after the noise floor are skipped. Returns
    an empty CloudStems whose ``spacing`` and ``noise_floor`` are the measured values (NaN,
    with ``reason``, when the cloud has no band points or no plausible slice fit). Values
    set in ``config`` are returned as given. Used by the scale-out engine's pilot region
    (:func:`stemmap.engine.catalog_statistics`).
    """
    cfg = replace(config or StemConfig(), estimate_height=False)
    return detect_prepared(prepare_cloud(xyz, cfg, origins=origins), cfg, statistics_only=True)


def grid_anchors(
    prepared: PreparedCloud, config: StemConfig, spacing: float
) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """(vertical-filter anchor, clustering anchor) of :func:`detect_prepared` on this cloud
    without ``grid_origin``, given its measured point ``spacing`` (``CloudStems.spacing``);
    None for an empty band. A part of the cloud run with ``StemConfig(filter_origin=,
    grid_origin=)`` set to them uses the same grid cells as the whole
    (:func:`~stemmap.cloud.band._grid_anchors`; the tile engine's pilot region)."""
    if prepared.band is None:
        return None
    cfg = _slice_setup(config, prepared.zmin, prepared.zmax, prepared.is_slice)
    return _grid_anchors(prepared.band, cfg, spacing, prepared.is_slice)


@dataclass
class PreparedCloud:
    """A cloud after our detector's ground step: its slice band (points with heights above
    the ground, the canopy raster when heights are estimated, sensor positions) and the z
    range and slice mode that adapt the configuration to a pre-cut slice.

    :func:`prepare_cloud` then :func:`detect_prepared` is :func:`detect_stems`. The ground
    step reads only ``slice_mode``, ``ground_cell``, ``max_memory``, ``max_diameter``,
    ``band`` and ``estimate_height`` of the configuration, so the scale-out engine prepares
    a chunk while the catalog's spacing and noise floor are still being measured and
    detects with them afterwards. ``band`` is None for an empty cloud.
    """

    band: _Band | None
    zmin: float = math.nan
    zmax: float = math.nan
    is_slice: bool = False

    def to_columns(self) -> dict[str, Any]:
        """Named arrays (no objects) for an .npz; :meth:`from_columns` reads them back."""
        if self.band is None:
            return {"empty": np.array(True)}
        b = self.band
        cols: dict[str, Any] = {
            "empty": np.array(False),
            "xy": b.xy,
            "h": b.h,
            "z": b.z,
            "base": np.array(b.base),
            "base_z": np.array(b.base_z),
            "zrange": np.array([self.zmin, self.zmax]),
            "is_slice": np.array(self.is_slice),
        }
        if b.canopy:
            cols["canopy_keys"], cols["canopy_h"] = b.canopy["keys"], b.canopy["h"]
        if b.origins is not None:
            cols["origins"] = np.ascontiguousarray(b.origins)
        if b.reach is not None:  # the 0.5-3 m returns of the shared-axis fit (axis_reach)
            cols["reach_xy"], cols["reach_h"] = b.reach
        return cols

    @classmethod
    def from_columns(cls, cols: dict[str, Any]) -> PreparedCloud:
        if bool(cols["empty"]):
            return cls(None)
        canopy = (
            {"keys": cols["canopy_keys"], "h": cols["canopy_h"]} if "canopy_keys" in cols else {}
        )
        band = _Band(
            cols["xy"],
            cols["h"],
            cols["z"],
            canopy,
            origins=cols.get("origins"),
            base=str(cols["base"]),
            base_z=float(cols.get("base_z", math.nan)),
        )
        if "reach_xy" in cols:
            band.reach = (cols["reach_xy"], cols["reach_h"])
        z0, z1 = (float(v) for v in cols["zrange"])
        return cls(band, z0, z1, bool(cols["is_slice"]))


def detect_prepared(
    prepared: PreparedCloud,
    config: StemConfig | None = None,
    *,
    statistics_only: bool = False,
    region: tuple[float, float, float, float] | None = None,
) -> CloudStems:
    """Stems of a :class:`PreparedCloud` (the steps of :func:`detect_stems` after the
    ground); with ``statistics_only`` only the spacing and noise floor
    (:func:`detect_statistics`). ``config`` must be the one the cloud was prepared with, up
    to ``spacing`` / ``noise_floor`` / ``grid_origin`` and the fit settings.

    ``region`` (xmin, ymin, xmax, ymax, metres; infinite sides allowed): only the stems in
    it are wanted (a tile engine's chunk keeps those its owned area holds); clusters far
    from it are not fitted. Stems inside it are the same as without it; outside it some are
    missing. Used only when ``config.noise_floor`` is given."""
    if prepared.band is None:
        return CloudStems.empty("ours", reason="the cloud is empty")
    cfg = _slice_setup(config or StemConfig(), prepared.zmin, prepared.zmax, prepared.is_slice)
    return _said_of_base(
        _stems_from_band(
            prepared.band,
            cfg,
            slice_cloud=prepared.is_slice,
            statistics_only=statistics_only,
            region=region,
        ),
        prepared.band,
    )


#: What an empty result of a cloud taken for a tree without ground adds to its reason.
STEM_BASE_NOTE = (
    "; no ground was found, so heights were measured from the cloud's lowest points as "
    "a segmented tree's stem base (if this is a plot, its lowest returns were too sparse "
    "to show its ground; detect_stems(ground=...) takes a ground model)"
)


def _said_of_base(result: CloudStems, band: _Band) -> CloudStems:
    """``result`` with the base its heights were measured from (``base``, and ``base_z`` for
    a flat base: the run's summary states it). An empty result of a cloud taken for a tree
    without ground also says so in its reason:
    its heights were measured from its lowest points, and if those were not a stem's cut
    (a plot's sparse lowest returns) the band was cut at the wrong height
    (docs/algorithms/cloud.md "Thinned plots: the ground, not a stem base")."""
    result = replace(result, base=band.base, base_z=band.base_z)
    if len(result) or band.base != BASE_STEM or result.reason == "statistics only":
        return result
    return replace(result, reason=result.reason + STEM_BASE_NOTE)


def prepare_cloud(
    xyz: ArrayLike,
    config: StemConfig | None = None,
    *,
    ground: GroundModel | None = None,
    origins: ArrayLike | None = None,
    ground_window: tuple[float, float, float, float] | None = None,
    base: tuple[str, float] | None = None,
    z_range: tuple[float, float] | None = None,
) -> PreparedCloud:
    """Our detector's ground step on an in-memory cloud (:class:`PreparedCloud`; the
    parameters are :func:`detect_stems`'s).

    ``ground_window`` (xmin, ymin, xmax, ymax): the cloud is the part of a larger one within
    this box (a tile engine's buffered chunk); the ground raster spans the cells of
    ``config.ground_extent`` within it (:meth:`GroundAccumulator.model`).

    ``base`` (what, z): the larger cloud's height reference, decided on all of it
    (:func:`_ground_model`), instead of deciding it on these points -- ``("ground", nan)``
    for a ground raster, ``("lowest stem points", z)`` for the flat base at z of a tree
    without ground. A tile engine's chunk holding only crown points (or a sliver of a plot)
    would otherwise take its own lowest points for a stem base, or a ground-less tree's
    crown for ground.

    ``z_range`` (zmin, zmax): the larger cloud's z extent, which decides the slice mode
    (``"auto"``) and lays out the sub-slices of a pre-cut slice (:func:`_slice_setup`):
    a chunk of a slice holds only part of its z range."""
    cfg = config or StemConfig()
    p = as_xyz(xyz)
    if p.shape[0] == 0:
        return PreparedCloud(None)
    o: FloatArray | None = None
    if origins is not None:
        if cfg.fit_method == "kasa":
            raise ConfigError(
                "origins are used only by the geometric fit (preset 'ours'); the Kasa fit has "
                "no along-ray refinement. Drop origins or use fit_method='ours'."
            )
        o = np.asarray(origins, dtype=np.float64)
        if o.shape == (3,) or o.shape == (2,):
            o = np.broadcast_to(o[:2], (p.shape[0], 2))
        elif o.ndim == 2 and o.shape[0] == p.shape[0] and o.shape[1] in (2, 3):
            o = o[:, :2]
        else:
            raise InputError(
                f"origins must have shape (3,) or (N, 3) with N = {p.shape[0]}, got {o.shape}."
            )
        if not np.all(np.isfinite(o)):
            raise InputError("origins hold non-finite values.")
    zmin, zmax = float(p[:, 2].min()), float(p[:, 2].max())
    if z_range is not None:
        zmin, zmax = (float(v) for v in z_range)
    is_slice = cfg.slice_mode == "always" or (cfg.slice_mode == "auto" and zmax - zmin < 1.0)
    if is_slice:
        band = _Band(p[:, :2], p[:, 2], p[:, 2], origins=o, base=BASE_SLICE)
    else:
        g = ground or _ground_of([p], cfg, _raster_extent(cfg.ground_extent, ground_window), base)
        lo, hi = cfg.band
        r_lo, r_hi = _reach_range(cfg)
        h, m = g.band_of(p, r_lo, r_hi)  # heights, and the indices of the band's points
        m, reach = _split_reach(p, h, m, lo, hi)
        o_m = None if o is None else o[m]
        band = _Band(p[m, :2], h[m], p[m, 2], origins=o_m, base=g.base, base_z=g.flat_z)
        band.reach = reach
        if cfg.estimate_height:
            band.canopy = _canopy_update({}, p[:, :2], h)
    return PreparedCloud(band, zmin, zmax, is_slice)


def _raster_extent(
    extent: tuple[float, float, float, float] | None,
    window: tuple[float, float, float, float] | None,
) -> tuple[float, float, float, float] | None:
    """The box the ground raster must span: ``extent`` cut to ``window`` (None: no box)."""
    if extent is None:
        return None
    if window is None:
        return extent
    x0, y0 = max(extent[0], window[0]), max(extent[1], window[1])
    x1, y1 = min(extent[2], window[2]), min(extent[3], window[3])
    return (x0, y0, x1, y1) if x0 <= x1 and y0 <= y1 else None


def _ground_of(
    chunks: Iterable[FloatArray],
    cfg: StemConfig,
    extent: tuple[float, float, float, float] | None = None,
    base: tuple[str, float] | None = None,
) -> GroundModel:
    acc = GroundAccumulator(cfg.ground_cell, cfg.max_memory)
    for c in chunks:
        acc.update(c)
    return _ground_model(acc, cfg, extent, base)


def _ground_model(
    acc: GroundAccumulator,
    cfg: StemConfig,
    extent: tuple[float, float, float, float] | None = None,
    base: tuple[str, float] | None = None,
) -> GroundModel:
    """The ground raster, or for a cloud without ground (one segmented tree) a flat base at
    its stem's lowest points (:meth:`GroundAccumulator.stem_base`). ``base``: the decision
    made on a larger cloud this one is part of (:func:`prepare_cloud`)."""
    if base is not None:
        what, z = base
        if what == BASE_STEM:
            return acc.flat(z, BASE_STEM)
        if what != BASE_GROUND:
            raise ConfigError(f"base must be {BASE_GROUND!r} or {BASE_STEM!r}, got {what!r}.")
        return acc.model(extent=extent)
    z_base = acc.stem_base(cfg.max_diameter)
    if z_base is not None:
        log.info(
            "no ground in the cloud (its lowest 0.5 m fit inside %.1f m): heights from the "
            "stem's lowest points, z = %.3f",
            cfg.max_diameter,
            z_base,
        )
        return acc.flat(z_base, BASE_STEM)
    return acc.model(extent=extent)


def detect_stems_file(
    path: str | Path,
    config: StemConfig | MunjerConfig | None = None,
    *,
    chunk_size: int = 2_000_000,
    on_chunk: Callable[[int, int], None] | None = None,
    sensor: SensorPositions | None = None,
    topic: str | None = None,
    on_ground: Callable[[GroundModel | None], None] | None = None,
    convention: CloudConvention | None = None,
) -> CloudStems:
    """Run a detector on a cloud file, streaming LAS/LAZ in chunks.

    ``StemConfig`` (ours) on LAS/LAZ: pass 1 builds the ground raster (and z range), pass 2
    keeps only the slice band (and a canopy-height raster if heights are requested); memory is
    bounded by the chunk size plus the band. Other formats (PLY, PCD, text, bags: ``topic``)
    are read whole and go to :func:`detect_stems`. ``MunjerConfig``: the cloud is read whole
    (a lidar frame is small).

    ``sensor`` gives each point's sensor position (a station, or a trajectory interpolated at
    the points' time stamps, :class:`stemmap.cloud.sensor.SensorPositions`) for the along-ray
    refinement of the slice fits (``detect_stems(..., origins=)``). Only ``ours`` uses it:
    with ``munjer2025`` or the Kasa fit it is a ConfigError rather than silently ignored.

    ``on_chunk(points_done, points_total)`` is called after each chunk of each pass (for a
    progress bar; ``points_total`` counts both passes).

    ``on_ground(model)`` (``ours`` only) receives the ground model the heights were measured
    from (``None`` when the cloud is read as one slice), so a caller that also wants the
    terrain (``stemmap stems --dtm``) does not stream the file again.

    ``convention`` (:class:`stemmap.io.conventions.CloudConvention`): the file's length unit
    and up axis; every chunk is converted to metres, z up as it is read, and the stems come
    out in that converted frame.
    """
    from stemmap.io.clouds import (
        count_points,
        iter_cloud_chunks,
        point_fields,
        read_cloud,
        read_plot_cloud,
    )

    cfg = config or StemConfig()
    src = repr(str(path))
    if sensor is not None and (isinstance(cfg, MunjerConfig) or cfg.fit_method == "kasa"):
        name = "munjer2025" if isinstance(cfg, MunjerConfig) else "the Kasa fit (ours_kasa)"
        raise ConfigError(
            f"sensor positions are used only by preset 'ours'; {name} has no along-ray "
            "refinement. Drop the sensor positions or use preset 'ours'."
        )
    if isinstance(cfg, MunjerConfig) or Path(path).suffix.lower() not in (".las", ".laz"):
        # munjer2025 reads one lidar frame (all NaN: a blocked sensor, no stems); a plot of
        # NaN is a broken export
        reader = read_cloud if isinstance(cfg, MunjerConfig) else read_plot_cloud
        cloud = reader(path, topic=topic, convention=convention)
        if on_chunk:
            on_chunk(len(cloud), len(cloud))
        if isinstance(cfg, MunjerConfig):
            return detect_stems_munjer(cloud.xyz, cfg)
        if on_ground is not None:
            z = cloud.xyz[:, 2]
            flat = len(z) == 0 or cfg.slice_mode == "always"
            flat = flat or (cfg.slice_mode == "auto" and float(z.max() - z.min()) < 1.0)
            on_ground(None if flat else _ground_of([cloud.xyz], cfg, cfg.ground_extent))
        origins = None
        if sensor is not None:
            times = None
            if sensor.needs_time:
                times = cloud.fields[sensor.pick_time_field(cloud.fields, src)]
            origins = sensor.origins(len(cloud), times, src)
        with naming_the_source(src):
            return detect_stems(cloud.xyz, cfg, origins=origins)
    tfield: str | None = None
    if sensor is not None and sensor.needs_time:
        tfield = sensor.pick_time_field(point_fields(path) or (), src)
    total = count_points(path)
    done = 0
    acc = GroundAccumulator(cfg.ground_cell, cfg.max_memory)
    zmin, zmax = math.inf, -math.inf
    n_total = 0
    for chunk in iter_cloud_chunks(path, chunk_size, convention=convention):
        xyz = chunk.xyz
        if xyz.shape[0] == 0:
            continue
        n_total += xyz.shape[0]
        zmin = min(zmin, float(xyz[:, 2].min()))
        zmax = max(zmax, float(xyz[:, 2].max()))
        acc.update(xyz)
        done += xyz.shape[0]
        if on_chunk:
            on_chunk(done, 2 * (total or n_total))
    if n_total == 0:
        raise InputError(f"{src} holds no points.")
    is_slice = cfg.slice_mode == "always" or (cfg.slice_mode == "auto" and zmax - zmin < 1.0)
    cfg = _slice_setup(cfg, zmin, zmax, is_slice)
    ground = None if is_slice else _ground_model(acc, cfg, cfg.ground_extent)
    if on_ground is not None:
        on_ground(ground)
    lo, hi = cfg.band
    r_lo, r_hi = _reach_range(cfg) if ground is not None else (lo, hi)
    xs, hs, zs, os_ = [], [], [], []
    rxs: list[FloatArray] = []
    rhs: list[FloatArray] = []
    canopy: dict[str, Any] = {}
    for chunk in iter_cloud_chunks(
        path, chunk_size, fields=(tfield,) if tfield else (), convention=convention
    ):
        xyz = chunk.xyz
        if ground is None:
            h = xyz[:, 2]
            m = np.flatnonzero((h >= lo) & (h <= hi))
        else:
            h, m = ground.band_of(xyz, r_lo, r_hi)  # heights, indices of the band's points
            m, reach = _split_reach(xyz, h, m, lo, hi)
            if reach is not None:
                rxs.append(reach[0])
                rhs.append(reach[1])
            if cfg.estimate_height:
                canopy = _canopy_update(canopy, xyz[:, :2], h)
        xs.append(xyz[m, :2])
        hs.append(h[m])
        zs.append(xyz[m, 2])
        if sensor is not None:  # only the band's points need a sensor position
            times = None if tfield is None else chunk.fields[tfield][m]
            os_.append(sensor.origins(int(m.size), times, src))
        done += xyz.shape[0]
        if on_chunk:
            on_chunk(done, 2 * n_total)
    band = _Band(
        np.concatenate(xs),
        np.concatenate(hs),
        np.concatenate(zs),
        canopy,
        origins=np.concatenate(os_) if sensor is not None else None,
        base=BASE_SLICE if ground is None else ground.base,
        base_z=math.nan if ground is None else ground.flat_z,
    )
    if rxs:
        band.reach = (np.concatenate(rxs), np.concatenate(rhs))
    log.info("%s: %d points, %d in the slice band", path, n_total, band.xy.shape[0])
    with naming_the_source(src):
        return _said_of_base(_stems_from_band(band, cfg, slice_cloud=is_slice), band)
