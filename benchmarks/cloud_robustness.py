"""Benchmark: the real clouds of ../shared/datasets as a user's export would have them.

Every cloud of ``cloud_real.py`` goes through ``detect_stems_file`` (the call ``stemmap stems``
makes, preset ours) once as shipped (the baseline) and once per transform, each transform
alone, written to a temporary LAS file (0.1 mm scale unless the transform says otherwise) and
read back through stemmap's reader:

* ``utm_las`` / ``utm_laz``: x + 500 000, y + 6 200 000, z + 300 m (a UTM export), stored with
  a 1 mm scale and the offset rounded down to 1 km (LAS, then LAZ); ``utm_ply_float32``: the
  same coordinates in a float32 PLY (an export without the global shift: float32 steps are
  3 cm at x = 500 000 and 50 cm at y = 6 200 000; the reader warns); ``las_scale_10cm``: the
  cloud as shipped in a LAS with a 0.1 m scale factor;
* ``subsample_50|20|10``: a random 50 / 20 / 10 % of the points; ``voxel_1cm|2cm``: one point
  per voxel, the mean of its points;
* ``noise_5mm|1cm``: isotropic Gaussian noise of that standard deviation per axis;
* ``tilt_5|10``: the whole cloud rotated by 5 / 10 degrees about a horizontal axis through its
  centre (an unlevelled scanner); ``rotate_z_30``: 30 degrees about the vertical;
* ``crop_0.3|0.8``: the points less than 0.3 / 0.8 m above the ground (the baseline's ground
  model, or its stem base) removed -- what a segmented tree's export looks like;
* ``quantise_1cm``: coordinates rounded to 1 cm; ``duplicate``: every point twice.

Per cloud and transform: stems found, matched to the baseline's (within half a diameter + 10
cm, after mapping the detections back through a rigid transform), DBH and position change
against the baseline, and DBH against the fixed ring reference each detection pairs with
(``_cloud_refs``, as cloud_real.py: converged from committed seeds, not from any detector run,
so the yardstick is the same for every transform and every version of the detector;
``references`` lists them with their spread over 15 start circles). For the crops the base
moves up, so DBH is measured higher: they are also compared with the ring of the cropped cloud
at the detection's own height (converged from starts about the detected circle: that comparison
is tied to the detection's height, so it cannot be fixed), and a single tree's with the shipped
cloud's DBH at the same absolute height (``dbh_vs_shipped_same_height_cm``: slices and breast
height raised by the base's rise; informational, crop invariance); a plot's crop also reports
the RMSE and bias against those own-height rings over its full-ring stems
(``dbh_vs_own_ring_rmse_cm``, ``dbh_vs_own_ring_bias_cm``; informational). A plot's crop is
judged (Dec 5) against each stem's fixed seed followed up to the detection's height
(``_cloud_refs.tracked_reference``: rings 0.1 m apart, each started from the one below; no
detector input but the height), over the rings that are full and within
``TRACKED_RMS_FACTOR`` (3) x the median RMS of the cloud's fixed full rings
(``dbh_vs_tracked_ring_rmse_cm`` / ``_bias_cm``, ``tracked_rings_full``): the crop moves the
base up, the detector states where it measured, and against the 1.3 m rings the cell read the
stems' taper (docs/algorithms/cloud.md "Cropped plots: the yardstick at the measured height");
the fixed 1.3 m RMSE stays in ``dbh_vs_ring_rmse_cm``. A transform fails a cloud when it misses
the issue-11 target there: a single tree not found, more than 1.5 cm off its ring, or, where
it has no full ring (aRchi Tree_1), moved more than 1.5 cm from the shipped tree's DBH (a crop: its
own-height ring, except where the shipped cloud measured at the same height misses that ring
too and the crop did not move the DBH by more than 1.5 cm -- the detector's miss at that
height, not the export's: listed under ``baseline_misses_too_cm``, docs/algorithms/cloud.md
"archi Tree_1 cropped at 0.3 m: the baseline at the same height"); a plot or
a slice with recall below 0.95 of the baseline's *checked* stems, extra stems above 5 %, or DBH
RMSE over its full rings above 1 cm (a crop: the tracked rings). A baseline stem is checked
when it pairs with a fixed ring reference: a detection with no ring at breast height cannot be
told from clutter by this benchmark (treels pine_plot's 6.3 cm edge object: no return within 15
cm of its axis at 1.30-1.50 m and none within 50 cm at 1.71-2.88 m, docs/algorithms/cloud.md
"pine_plot's 17th stem"); losing one is listed (``missed_unchecked_dbh_cm``), not failed. Crops
and tilts do not apply to pre-cut slices (fortls_slice, lidr_dbh: heights are given, there is
no stem base to crop to, and a slice cut from a tilted scan is cut in the scanner's frame).

Refusals. ``stemmap stems`` refuses a cloud whose x or y coordinates near the stems are
rounded to a step above ``MAX_COORDINATE_STEP`` (2 cm; ``stemmap.cloud.quantisation``). The
benchmark knows each file's resolution from its format, independently of the detector (LAS:
the header's x / y scale; float32 PLY: the float32 step at the largest |x| and |y|): a
refusal where that resolution is above the bound is a correct result, listed under
``refused`` with its reason and not failed; a refusal where it is not is a failure
(``refused: ...``), and so is a result where it is (``not refused: ...``: numbers from a grid
too coarse to trust).

``--seed N`` draws the random transforms from seed N (0 by default; ``cloud_loo.py`` runs
seeds 0-4); ``--set key=value`` runs the transforms (not the baseline, the yardstick) with
that :class:`StemConfig` option (true / false / a number).

Prints ONE JSON object. Usage: python benchmarks/cloud_robustness.py [--clouds a,b]
[--transforms t1,t2] [--seed N] [--set key=value ...]
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import laspy
import numpy as np

from _cloud_refs import (
    RingSeed,
    fixed_references,
    load_seeds,
    reference_of_each,
    tracked_reference,
)
from _cloud_refs import match_stems as _match
from _datasets import require_datasets_dir
from cloud_real import CLOUDS  # the clouds cloud_real.py measures
from stemmap.cloud.filters import voxel_downsample
from stemmap.cloud.ground import GroundModel
from stemmap.cloud.quantisation import MAX_COORDINATE_STEP, QuantisedCoordinatesError
from stemmap.cloud.reference import RingReference, converged_ring_reference
from stemmap.cloud.result import BASE_SLICE, CloudStems
from stemmap.cloud.stems import StemConfig, detect_stems, detect_stems_file
from stemmap.io.clouds import read_cloud

UTM = np.array([500_000.0, 6_200_000.0, 300.0])
SLICES = ("fortls_slice", "lidr_dbh")


@dataclass(frozen=True)
class Prepared:
    """A transformed cloud, how to write it, and the rigid map back to the original frame
    (``orig = R.T @ (p - c - t) + c``; identity for non-rigid transforms)."""

    xyz: np.ndarray
    suffix: str = ".las"
    scale: float = 1e-4
    offset_round: float = 1.0  # LAS offset: the minimum rounded down to this (m)
    rot: np.ndarray | None = None
    center: np.ndarray | None = None
    shift: np.ndarray | None = None

    def back(self, p: np.ndarray) -> np.ndarray:
        q = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        if self.shift is not None:
            q = q - self.shift
        if self.rot is not None and self.center is not None:
            q = (q - self.center) @ self.rot + self.center
        return q


@dataclass(frozen=True)
class Context:
    """What the transforms need from the baseline run."""

    xyz: np.ndarray
    ground: GroundModel | None
    rng_seed: int = 0


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * (k @ k)


def _rigid(ctx: Context, rot: np.ndarray) -> Prepared:
    c = np.array([*np.median(ctx.xyz[:, :2], axis=0), float(ctx.xyz[:, 2].min())])
    return Prepared((ctx.xyz - c) @ rot.T + c, rot=rot, center=c)


def _subsample(frac: float) -> Callable[[Context], Prepared]:
    def f(ctx: Context) -> Prepared:
        n = ctx.xyz.shape[0]
        idx = np.sort(np.random.default_rng(ctx.rng_seed).choice(n, int(frac * n), replace=False))
        return Prepared(ctx.xyz[idx])

    return f


def _noise(sigma: float) -> Callable[[Context], Prepared]:
    def f(ctx: Context) -> Prepared:
        gen = np.random.default_rng(ctx.rng_seed)
        return Prepared(ctx.xyz + gen.normal(0.0, sigma, ctx.xyz.shape))

    return f


def _crop(level: float) -> Callable[[Context], Prepared | None]:
    def f(ctx: Context) -> Prepared | None:
        if ctx.ground is None:
            return None
        return Prepared(ctx.xyz[ctx.ground.height_of(ctx.xyz) >= level])

    return f


def write_ply_float32(path: Path, xyz: np.ndarray) -> None:
    """``xyz`` as a binary little-endian PLY with float32 x, y, z (Open3D's and many
    exporters' default)."""
    head = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {xyz.shape[0]}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    with open(path, "wb") as f:
        f.write(head.encode("ascii"))
        f.write(np.ascontiguousarray(xyz, dtype="<f4").tobytes())


def _utm(suffix: str) -> Callable[[Context], Prepared]:
    def f(ctx: Context) -> Prepared:
        return Prepared(ctx.xyz + UTM, suffix=suffix, scale=1e-3, offset_round=1000.0, shift=UTM)

    return f


TILT_AXIS = np.array([math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0])
TRANSFORMS: dict[str, Callable[[Context], Prepared | None]] = {
    "identity_las": lambda ctx: Prepared(ctx.xyz),
    "utm_las": _utm(".las"),
    "utm_laz": _utm(".laz"),
    "utm_ply_float32": _utm(".ply"),
    "subsample_50": _subsample(0.5),
    "subsample_20": _subsample(0.2),
    "subsample_10": _subsample(0.1),
    "voxel_1cm": lambda ctx: Prepared(np.asarray(voxel_downsample(ctx.xyz, 0.01))),
    "voxel_2cm": lambda ctx: Prepared(np.asarray(voxel_downsample(ctx.xyz, 0.02))),
    "noise_5mm": _noise(0.005),
    "noise_1cm": _noise(0.01),
    "tilt_5": lambda ctx: _rigid(ctx, _rot(TILT_AXIS, 5.0)),
    "tilt_10": lambda ctx: _rigid(ctx, _rot(TILT_AXIS, 10.0)),
    "rotate_z_30": lambda ctx: _rigid(ctx, _rot(np.array([0.0, 0.0, 1.0]), 30.0)),
    "crop_0.3": _crop(0.3),
    "crop_0.8": _crop(0.8),
    "quantise_1cm": lambda ctx: Prepared(np.round(ctx.xyz, 2)),
    "las_scale_10cm": lambda ctx: Prepared(ctx.xyz, scale=0.1),
    "duplicate": lambda ctx: Prepared(np.repeat(ctx.xyz, 2, axis=0)),
}
NOT_FOR_SLICES = ("tilt_5", "tilt_10", "crop_0.3", "crop_0.8")


def write_las(path: Path, xyz: np.ndarray, scale: float, offset_round: float) -> None:
    """``xyz`` as a LAS/LAZ 1.2 file (point format 0) with ``scale`` and the offset at the
    minimum rounded down to ``offset_round`` metres (what exporters do)."""
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = np.full(3, scale)
    header.offsets = np.floor(xyz.min(axis=0) / offset_round) * offset_round
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.write(str(path))


def format_resolution(prep: Prepared) -> float:
    """The horizontal resolution the file format gives the transformed cloud (m), known
    without the detector: the LAS scale, or the float32 step at the largest |x| and |y|."""
    if prep.suffix == ".ply":
        big = np.abs(prep.xyz[:, :2]).max(axis=0).astype(np.float32)
        return float(np.spacing(big).max())
    return float(prep.scale)


def refused_row(name: str, prep: Prepared, exc: QuantisedCoordinatesError) -> dict[str, Any]:
    """A refused run: its reason, and whether the file's format resolution called for it."""
    res = format_resolution(prep)
    expected = res > MAX_COORDINATE_STEP
    return {
        "refused": str(exc),
        "format_resolution_m": res,
        "measured_step_m": [_r(v, 4) for v in exc.steps],
        "fails": [] if expected else [f"refused: {exc}"],
    }


#: a ring followed up a stem (:func:`_cloud_refs.tracked_reference`) is a reference for a
#: cropped plot where it is full and its RMS is at most this times the median RMS of the
#: cloud's fixed full rings -- the detector's residual test (``StemConfig.residual_factor``)
#: applied to the yardstick: at 1.9-2.2 m treels pine_plot's stems enter the crown base and a
#: ring there can fit a branch whorl (38-50 mm RMS against 3-10 mm on the stems)
TRACKED_RMS_FACTOR = 3.0


#: issue 11: a single tree's DBH within this of its ring reference (cm)
SINGLE_TREE_TOL_CM = 1.5


def set_value(v: str) -> Any:
    """A ``--set`` value: true / false, a number, else the text (``dbh_from=median``)."""
    low = v.strip().lower()
    if low in ("true", "false"):
        return low == "true"
    try:
        return float(v)
    except ValueError:
        return v.strip()


def set_overrides(pairs: list[str]) -> dict[str, Any]:
    """The ``--set key=value`` arguments as :class:`StemConfig` overrides."""
    return {k: set_value(v) for k, v in (kv.split("=", 1) for kv in pairs)}


def _r(v: float, nd: int = 2) -> float | None:
    return round(float(v), nd) if np.isfinite(v) else None


def _score(
    name: str,
    base: CloudStems,
    refs: list[RingReference | None],
    seeds: list[RingSeed],
    det: CloudStems,
    prep: Prepared,
    xyz_t: np.ndarray,
    single: bool,
    checked: frozenset[int] | None = None,
) -> dict[str, Any]:
    """Compare one transformed run with the baseline (``checked``: the baseline stems a
    plot's recall is counted over, by default all)."""
    checked = frozenset(range(len(base))) if checked is None else checked
    zbh = det.z if det.base != BASE_SLICE else np.full(len(det), np.nan)
    back = prep.back(np.column_stack((det.xy, np.nan_to_num(zbh))))
    pairs = _match(base.xy, base.diameter, back[:, :2])
    dd = np.array([det.diameter[j] - base.diameter[i] for i, j in pairs])
    dp = np.array([np.hypot(*(back[j, :2] - base.xy[i])) for i, j in pairs])
    hits = reference_of_each(refs, back[:, :2])
    err = np.array([det.diameter[j] - h[1].diameter for j, h in enumerate(hits) if h and h[1].full])
    row: dict[str, Any] = {
        "n_stems": len(det),
        "base": det.base,
        "matched": len(pairs),
        "missed": len(base) - len(pairs),
        "extra": len(det) - len(pairs),
        "missed_dbh_cm": [
            _r(100 * base.diameter[i])
            for i in sorted(set(range(len(base))) - {i for i, _ in pairs})
        ],
        "missed_unchecked_dbh_cm": [
            _r(100 * base.diameter[i])
            for i in sorted(set(range(len(base))) - {i for i, _ in pairs} - checked)
        ],
        "dbh_change_max_cm": _r(100 * np.abs(dd).max()) if dd.size else None,
        "dbh_change_mean_cm": _r(100 * dd.mean()) if dd.size else None,
        "pos_change_max_cm": _r(100 * dp.max()) if dp.size else None,
        "dbh_vs_ring_rmse_cm": _r(100 * np.sqrt(np.mean(err**2))) if err.size else None,
        "spacing_mm": _r(1000 * det.spacing, 1),
    }
    if not len(det):
        row["reason"] = det.reason
    e_pass = err  # what a plot's DBH RMSE test reads (a crop's: below)
    if name.startswith("crop"):
        # the cropped cloud's ring at the detection's own height: the height is the
        # detection's, so is the start (a leaning stem is centimetres off its 1.3 m seed at
        # 2.1 m); converged from 15 starts about it, of the seed's ring thickness
        own = [
            None
            if h is None
            else converged_ring_reference(
                xyz_t,
                (float(back[j, 0]), float(back[j, 1])),
                float(det.z[j]),
                float(det.diameter[j]) / 2,
                half_thickness=seeds[h[0]].half,
            )
            for j, h in enumerate(hits)
        ]
        e2 = [det.diameter[j] - r.diameter for j, r in enumerate(own) if r is not None]
        row["own_ring_dbh_cm"] = [None if r is None else _r(100 * r.diameter) for r in own]
        row["dbh_vs_own_ring_max_cm"] = _r(100 * np.abs(e2).max()) if e2 else None
        # informational (a plot's pass test reads the tracked rings below): the same
        # stems' error against the cropped cloud's ring at the height they were measured at,
        # over the detections whose fixed reference is a full ring
        e3 = np.array(
            [
                det.diameter[j] - r.diameter
                for j, (r, h) in enumerate(zip(own, hits, strict=True))
                if r is not None and h is not None and h[1].full
            ]
        )
        row["dbh_vs_own_ring_rmse_cm"] = _r(100 * np.sqrt(np.mean(e3**2))) if e3.size else None
        row["dbh_vs_own_ring_bias_cm"] = _r(100 * e3.mean()) if e3.size else None
        if not single:
            # the fixed seed's stem followed up to each detection's height (_cloud_refs.
            # tracked_reference: no detector input but the height): a plot's crop is judged on
            # these, over the rings that are references there: full, and of an RMS within
            # TRACKED_RMS_FACTOR x the median of the cloud's fixed full rings
            tracked = [
                None if h is None else tracked_reference(xyz_t, seeds[h[0]], float(det.z[j]))
                for j, h in enumerate(hits)
            ]
            full_rms = [r.rms for r in refs if r is not None and r.full]
            rms_max = TRACKED_RMS_FACTOR * float(np.median(full_rms)) if full_rms else 0.0
            e4 = np.array(
                [
                    det.diameter[j] - r.diameter
                    for j, r in enumerate(tracked)
                    if r is not None and r.full and r.rms <= rms_max
                ]
            )
            row["dbh_vs_tracked_ring_rmse_cm"] = (
                _r(100 * np.sqrt(np.mean(e4**2))) if e4.size else None
            )
            row["dbh_vs_tracked_ring_bias_cm"] = _r(100 * e4.mean()) if e4.size else None
            row["tracked_rings_full"] = int(e4.size)
            e_pass = e4
        row["dbh_height_above_true_base_m"] = [
            _r(float(det.z[j] - det.dbh_height[j]) - float(base.z[i] - base.dbh_height[i]) + 1.3)
            for i, j in pairs
        ]
    # issue 11 targets, relative to the baseline's stems
    why = []
    if single:
        if not pairs:
            why.append("stem not found")
        else:
            ref_err = row["dbh_vs_own_ring_max_cm"] if name.startswith("crop") else None
            e = ref_err if ref_err is not None else row["dbh_vs_ring_rmse_cm"]
            why += single_tree_dbh_fails(name, e, row["dbh_change_max_cm"])
    else:
        found = sum(1 for i, _ in pairs if i in checked)
        if found < 0.95 * len(checked):
            why.append(f"recall {found}/{len(checked)}")
        if row["extra"] > 0.05 * len(base):
            why.append(f"{row['extra']} extra stems")
        if e_pass.size and np.sqrt(np.mean(e_pass**2)) > 0.01:
            why.append(f"DBH RMSE {_r(100 * np.sqrt(np.mean(e_pass**2)))} cm")
    row["fails"] = why
    return row


def single_tree_dbh_fails(
    name: str, ring_err_cm: float | None, moved_cm: float | None
) -> list[str]:
    """Why a single tree's DBH fails transform ``name``: more than :data:`SINGLE_TREE_TOL_CM` off
    its ring (``ring_err_cm``), or, where it has no full ring to judge by (aRchi Tree_1 at
    breast height: ``ring_err_cm`` None), moved more than that from the shipped tree's DBH
    (``moved_cm``; the export must leave it where it was). A crop with no ring is not judged
    by the move: it measures at another height, so its change is taper, not error."""
    if ring_err_cm is not None:
        return (
            [f"DBH {ring_err_cm} cm off the ring"] if abs(ring_err_cm) > SINGLE_TREE_TOL_CM else []
        )
    if name.startswith("crop") or moved_cm is None or moved_cm <= SINGLE_TREE_TOL_CM:
        return []
    return [f"DBH moved {moved_cm} cm from the shipped tree's (no ring)"]


@dataclass(frozen=True)
class Baseline:
    """One cloud as shipped: its points, the detector's stems on it (what every transform is
    matched against), the ground model the crops cut at, the fixed ring references, and the
    stems that pair with one (``checked``: a plot's recall is counted over them)."""

    key: str
    xyz: np.ndarray
    det: CloudStems
    ground: GroundModel | None
    seeds: list[RingSeed]
    refs: list[RingReference | None]
    cpu_s: float
    checked: frozenset[int]


def run_baseline(key: str, path: Path, cfg: StemConfig | None = None) -> Baseline:
    """The baseline run of cloud ``key`` (preset ours, or ``cfg``) and its fixed references."""
    xyz = read_cloud(path).xyz
    grounds: list[GroundModel | None] = []
    t0 = time.process_time()
    det = detect_stems_file(path, cfg or StemConfig(), on_ground=grounds.append)
    cpu = time.process_time() - t0
    seeds = load_seeds()[key]
    refs = fixed_references(xyz, seeds)
    checked = frozenset(i for i, h in enumerate(reference_of_each(refs, det.xy)) if h)
    return Baseline(key, xyz, det, grounds[0] if grounds else None, seeds, refs, cpu, checked)


def transformed_files(
    bl: Baseline, names: list[str], tmp: Path, rng_seed: int = 0
) -> Iterator[tuple[str, Prepared, Path]]:
    """Each transform of ``names`` that applies to the cloud, written to a file in ``tmp``
    (random draws from ``rng_seed``); the file is removed when the next one is asked for."""
    ctx = Context(bl.xyz, bl.ground, rng_seed)
    for name in names:
        if bl.key in SLICES and name in NOT_FOR_SLICES:
            continue
        prep = TRANSFORMS[name](ctx)
        if prep is None:
            continue
        f = tmp / f"{bl.key}_{name}_{rng_seed}{prep.suffix}"
        if prep.suffix == ".ply":
            write_ply_float32(f, prep.xyz)
        else:
            write_las(f, prep.xyz, prep.scale, prep.offset_round)
        try:
            yield name, prep, f
        finally:
            f.unlink()


def score_run(name: str, bl: Baseline, det: CloudStems, prep: Prepared) -> dict[str, Any]:
    """One transformed run against the baseline's stems and the fixed references
    (:func:`_score`; ``fails`` lists the issue-11 targets it misses).

    A single tree's crop that misses its own-height ring is failed only where the baseline
    -- the shipped cloud, default preset, measured at the same absolute height
    (:func:`baseline_at_height`) -- meets that ring, or the crop moved the DBH away from the
    baseline's there by more than the tolerance: where the baseline misses the ring too and
    the crop's DBH is within the tolerance of it, the miss is the detector's at that height on
    the data as shipped, not what the export did, and is listed (``baseline_misses_too_cm``:
    the baseline's error there) instead of failed, as a plot's stem the baseline does not
    give is not counted against a transform (docs/algorithms/cloud.md "archi Tree_1 cropped
    at 0.3 m: the baseline at the same height")."""
    row = _score(name, bl.det, bl.refs, bl.seeds, det, prep, prep.xyz, len(bl.det) == 1, bl.checked)
    off = [f for f in row["fails"] if f.endswith("off the ring")]
    own = row.get("own_ring_dbh_cm") or [None]
    if off and name.startswith("crop") and len(det) == 1 and own[0] is not None:
        miss = baseline_misses_too(
            float(own[0]), float(det.diameter[0]), baseline_at_height(bl, det)
        )
        if miss is not None:
            row["baseline_misses_too_cm"] = _r(miss)
            row["fails"] = [f for f in row["fails"] if f not in off]
    return row


def baseline_misses_too(own_cm: float, det_m: float, same_m: float | None) -> float | None:
    """The baseline's error (cm) against a crop's own-height ring of ``own_cm`` where it
    misses that ring by more than :data:`SINGLE_TREE_TOL_CM` too and the crop's DBH
    ``det_m`` is within that tolerance of the baseline's at the same height ``same_m`` (m;
    None: no baseline there); else None (the crop's miss stands)."""
    if same_m is None:
        return None
    miss = 100 * same_m - own_cm
    moved = 100 * abs(det_m - same_m)
    return miss if abs(miss) > SINGLE_TREE_TOL_CM and moved <= SINGLE_TREE_TOL_CM else None


def baseline_at_height(
    bl: Baseline, det: CloudStems, cfg: StemConfig | None = None
) -> float | None:
    """The DBH (m) of a single tree's shipped cloud at the absolute height a crop's detection
    ``det`` was measured at: ``cfg`` (default: the baseline's preset) with the slices and
    breast height raised by the base's rise (None unless it gives one stem)."""
    cfg = cfg or StemConfig()
    rise = float(det.z[0] - det.dbh_height[0]) - float(bl.det.z[0] - bl.det.dbh_height[0])
    raised = replace(
        cfg,
        slice_centers=tuple(h + rise for h in cfg.slice_centers),
        breast_height=cfg.breast_height + rise,
    )
    same = detect_stems(bl.xyz, raised)
    return float(same.diameter[0]) if len(same) == 1 else None


def same_height_change(bl: Baseline, det: CloudStems, cfg: StemConfig) -> float | None:
    """A cropped single tree's DBH minus the shipped cloud's, measured at the same absolute
    height (:func:`baseline_at_height` with ``cfg``: the crop's only effect if the detector is
    crop-invariant). Informational."""
    same = baseline_at_height(bl, det, cfg)
    return None if same is None else _r(100 * (det.diameter[0] - same))


def run_cloud(
    key: str,
    path: Path,
    names: list[str],
    tmp: Path,
    seed: int = 0,
    overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    cfg = StemConfig()
    bl = run_baseline(key, path, cfg)
    cfg = replace(cfg, **(overrides or {}))  # the transforms' config; the baseline's is default
    base = bl.det
    out: dict[str, Any] = {
        "file": str(path),
        "n_points": int(bl.xyz.shape[0]),
        "baseline": {
            "n_stems": len(base),
            "base": base.base,
            "dbh_cm": [_r(100 * d) for d in base.diameter],
            "cpu_s": round(bl.cpu_s, 2),
        },
    }
    out["references"] = [
        None
        if r is None
        else {
            "ring_dbh_cm": _r(100 * r.diameter),
            "ring_spread_cm": _r(100 * r.spread),
            "ring_full": r.full,
        }
        for r in bl.refs
    ]
    base_err = np.array(
        [
            base.diameter[j] - h[1].diameter
            for j, h in enumerate(reference_of_each(bl.refs, base.xy))
            if h and h[1].full
        ]
    )
    out["baseline"]["dbh_vs_ring_rmse_cm"] = (
        _r(100 * np.sqrt(np.mean(base_err**2))) if base_err.size else None
    )
    out["baseline"]["unchecked_dbh_cm"] = [
        _r(100 * base.diameter[i]) for i in range(len(base)) if i not in bl.checked
    ]
    res: dict[str, Any] = {}
    for name, prep, f in transformed_files(bl, names, tmp, seed):
        t0 = time.process_time()
        try:
            det = detect_stems_file(f, cfg)
        except QuantisedCoordinatesError as exc:
            res[name] = refused_row(name, prep, exc)
            continue
        cpu = time.process_time() - t0
        row = score_run(name, bl, det, prep)
        if format_resolution(prep) > MAX_COORDINATE_STEP:
            row["fails"].append(
                f"not refused: the file's resolution is {format_resolution(prep):.3f} m"
            )
        if name.startswith("crop") and len(base) == 1 and len(det) == 1:
            row["dbh_vs_shipped_same_height_cm"] = same_height_change(bl, det, cfg)
        row["n_points"] = int(prep.xyz.shape[0])
        row["cpu_s"] = round(cpu, 2)
        res[name] = row
    out["transforms"] = res
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clouds", default=",".join(CLOUDS))
    ap.add_argument("--transforms", default=",".join(TRANSFORMS))
    ap.add_argument("--seed", type=int, default=0, help="seed of the random transforms")
    ap.add_argument("--set", action="append", default=[], help="StemConfig key=value")
    args = ap.parse_args()
    overrides = set_overrides(args.set)
    root = require_datasets_dir()
    names = args.transforms.split(",")
    t0 = time.process_time()
    with tempfile.TemporaryDirectory() as td:
        clouds = {
            k: run_cloud(k, root / CLOUDS[k], names, Path(td), args.seed, overrides)
            for k in args.clouds.split(",")
        }
    fails = {
        f"{k}/{t}": r["fails"]
        for k, c in clouds.items()
        for t, r in c["transforms"].items()
        if r["fails"]
    }
    misses_too = {
        f"{k}/{t}": r["baseline_misses_too_cm"]
        for k, c in clouds.items()
        for t, r in c["transforms"].items()
        if "baseline_misses_too_cm" in r
    }
    refused = {
        f"{k}/{t}": r["refused"]
        for k, c in clouds.items()
        for t, r in c["transforms"].items()
        if "refused" in r and not r["fails"]
    }
    out = {
        "benchmark": "cloud_robustness",
        "note": "preset ours through detect_stems_file; every transform written to LAS and read "
        "back; fails = issue-11 cloud targets missed relative to the baseline's stems (a "
        "plot's recall over those with a fixed ring reference); refused = cells refused as "
        "too coarse where the file's format resolution is above the bound (correct results, "
        "not failures)",
        "seed": args.seed,
        "set": overrides,
        "cpu_s": round(time.process_time() - t0, 1),
        "fails": fails,
        "refused": refused,
        "baseline_misses_too_cm": misses_too,
        "clouds": clouds,
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
