"""Pieces of ``real_geometry.py`` shared with ``real_geometry_diagnose.py`` and
``scan_noise.py``: the textbook detector, the virtual scanner settings, the detector set up
for a scanner, the vantage points on a real slice, greedy matching and error statistics. A
helper module, not a script; each benchmark imports it explicitly (the script's own folder is
on ``sys.path`` when it runs, from any working directory)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.eval.real_slices import (
    SLICES,
    Mount,
    RealSlice,
    Relief,
    load_slice,
    noisy_batch,
    virtual_scans,
)
from stemmap.eval.scan_background import RELIEF_CORR, RELIEF_STD
from stemmap.scan.detect import DetectorConfig
from stemmap.types import ScanBatch

__all__ = [
    "ANY_HIT",
    "AVERAGING_SCANNERS",
    "BACKGROUNDS",
    "FULL_SCANNERS",
    "QUICK_SCANNERS",
    "TEXTBOOK",
    "ReturnRule",
    "SceneBatch",
    "add_hit_fraction",
    "dataset_seed",
    "error_stats",
    "greedy_match",
    "matched",
    "scene_batches",
    "scene_note",
    "scene_scans",
    "slice_scan_batches",
    "vantage_points",
]


#: A textbook 2D trunk detector: range-jump segmentation (Zheng et al. 2012 eq. 2, 0.2 m),
#: >= 3 returns, the Kasa (1976) fit, radius 2 cm - 1 m; no plausibility test.
TEXTBOOK = DetectorConfig(
    name="textbook_kasa",
    segmentation="range_jump",
    max_jump=0.2,
    min_points=3,
    fit_method="kasa",
    min_radius=0.02,
    max_radius=1.0,
)


QUICK_SCANNERS = (("nearest", 0.5, 0.0), ("averaging", 0.5, 0.01))


FULL_SCANNERS = tuple(
    (m, res, noise)
    for m in ("nearest", "averaging")
    for res in (0.25, 0.5, 1.0)
    for noise in (0.0, 0.01, 0.03)
)

#: The return-threshold study (Dec 4): the averaging scanner at every resolution, noise 0 / 1 cm.
AVERAGING_SCANNERS = tuple(
    ("averaging", res, noise) for res in (0.25, 0.5, 1.0) for noise in (0.0, 0.01)
)


def matched(cfg: DetectorConfig, model: str, res: float) -> DetectorConfig:
    """``cfg`` set up for the scanner as a user does (``stemmap detect --footprint``): a
    first-echo (nearest-return) scanner whose beam fills the angular step has a footprint of
    one step (corrected before fitting); an averaging scanner keeps the preset's edge model."""
    if model == "nearest" and cfg.fit_method == "ours":
        return replace(cfg, beam_footprint_deg=res)
    return cfg


def vantage_points(
    sl: RealSlice, n: int, rng: np.random.Generator, r_lo: float = 1.0, r_hi: float = 15.0
) -> np.ndarray:
    """``n`` vantage points, each at a uniform range in [r_lo, r_hi] and a uniform bearing from
    a random reference trunk, >= 0.3 m from every slice point (not inside a trunk or bush)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(sl.xy)
    c = sl.centers
    out: list[np.ndarray] = []
    tries = 0
    while len(out) < n and tries < 100 * n:
        tries += 1
        t = int(rng.integers(c.shape[0]))
        d = float(rng.uniform(r_lo, r_hi))
        b = float(rng.uniform(-math.pi, math.pi))
        p = c[t] + d * np.array([math.cos(b), math.sin(b)])
        if tree.query(p)[0] >= 0.3:
            out.append(p)
    return np.asarray(out).reshape(-1, 2)


def greedy_match(det: np.ndarray, truth: np.ndarray, gate: np.ndarray) -> np.ndarray:
    """Greedy nearest-first matching; returns for each truth the matched detection or -1."""
    out = np.full(truth.shape[0], -1, dtype=np.int64)
    if det.shape[0] == 0 or truth.shape[0] == 0:
        return out
    dist = np.hypot(*(truth[:, None, :] - det[None, :, :]).transpose(2, 0, 1))
    used = np.zeros(det.shape[0], dtype=bool)
    for flat in np.argsort(dist, axis=None):
        t, k = divmod(int(flat), det.shape[0])
        if out[t] >= 0 or used[k] or dist[t, k] > gate[t]:
            continue
        out[t], used[k] = k, True
    return out


def error_stats(err_cm: np.ndarray) -> dict[str, Any]:
    e = err_cm[np.isfinite(err_cm)]
    if e.size == 0:
        return {"n": 0, "rmse_cm": None, "bias_cm": None}
    return {
        "n": int(e.size),
        "rmse_cm": round(float(np.sqrt(np.mean(e * e))), 2),
        "bias_cm": round(float(np.mean(e)), 2),
    }


#: What the virtual scans see besides the trunks (``--background``): ``ground`` (the
#: default since the fifteenth round) or ``none`` (trunks only, the first fourteen rounds).
BACKGROUNDS = ("ground", "none")

#: The mount of the ``ground`` scans: 1.3 m above the ground, pitched down 3 degrees.
MOUNT = Mount(height=1.3, pitch_deg=3.0, band=0.1)


def scene_scans(
    sl: RealSlice,
    vp: np.ndarray,
    model: str,
    res: float,
    background: str,
    seed: int,
    mount: Mount = MOUNT,
    relief_std: float = RELIEF_STD,
    relief_corr: float = RELIEF_CORR,
    return_rule: ReturnRule | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free virtual scans (ranges, hit trunk) of ``sl`` from ``vp``. ``background``
    ``"ground"``: the scan plane (``mount``, default :data:`MOUNT`) pitched towards a uniform
    random heading per vantage also returns from the slice's ground and understory
    (:attr:`RealSlice.ground`) and from the ground plane with a micro-relief (``relief_std``,
    ``relief_corr``: the TreeLS plot's by default,
    :meth:`stemmap.eval.scan_background.Relief.random`); headings and relief come from their
    own generators (``seed``), so the vantage points and the noise are those of ``"none"``.
    ``return_rule``: the averaging scanner's return threshold (:class:`ReturnRule`), which
    the averaging model needs (a ValueError without one: until Dec 6 it fell silently to any
    sub-ray, :data:`ANY_HIT`); ignored by the nearest-return model."""
    extra: dict[str, Any] = {}
    if model == "averaging":
        if return_rule is None:
            raise ValueError(
                "scene_scans: the averaging scanner needs its return rule: pass return_rule="
                "ReturnRule(q) (ANY_HIT: any sub-ray, every benchmark's rule before Dec 6)."
            )
        extra.update(return_rule.kwargs())
    if background == "ground":
        heads = np.random.default_rng((seed, 1)).uniform(-math.pi, math.pi, vp.shape[0])
        extra.update(  # keeps the return rule (an assignment here dropped it)
            {
                "background": "ground",
                "ground": sl.ground,
                "mount": mount,
                "headings": heads,
                "relief": Relief.random(60.0, seed, relief_std, relief_corr),
            }
        )
    return virtual_scans(
        sl.xy, sl.labels, vp, resolution_deg=res, model=model, centers=sl.centers, **extra
    )


@dataclass(frozen=True)
class ReturnRule:
    """When a virtual averaging (SICK-class) beam returns (Dec 4, "Averaging scanners: the
    return threshold"): at least ``min_hit_fraction`` of its 0.25-degree footprint, sampled by
    ``sub_rays`` sub-rays of a ``profile`` beam, must hit (see
    :func:`stemmap.eval.real_slices.virtual_scans`; the range model is the simulator's,
    :mod:`stemmap.sim.footprint`). The default is the real SICK LMS200's measured threshold,
    0.3 of the footprint, the simulator's ``sick_lms`` preset's too (any sub-ray before Dec 6,
    "One return threshold"), with 25 sub-rays (5 before Dec 5, "Mixed pixels: one footprint
    model")."""

    min_hit_fraction: float = 0.3
    profile: str = "uniform"
    sub_rays: int = 25

    def kwargs(self) -> dict[str, Any]:
        return {
            "min_hit_fraction": self.min_hit_fraction,
            "beam_profile": self.profile,
            "sub_rays": self.sub_rays,
        }

    def note(self) -> str:
        share = "any sub-ray" if self.min_hit_fraction == 0 else f"{self.min_hit_fraction:g}"
        return f"{share} of {self.sub_rays} {self.profile} sub-rays"


#: The averaging scanner's rule of every benchmark before Dec 6 ("One return threshold"): a beam
#: returns when any of its 25 uniform sub-rays hits -- ``virtual_scans``' own defaults, so a
#: script that passes it gives the numbers it gave without a rule. Scripts whose published
#: numbers were measured so pass it by name (or as their ``--hit-fraction 0`` default).
ANY_HIT = ReturnRule(0.0)


def add_hit_fraction(ap: argparse.ArgumentParser, default: ReturnRule) -> None:
    """``--hit-fraction`` as ``real_geometry.py``'s (the virtual averaging scanner's return
    threshold: the share of its footprint that must hit), default ``default``'s; the script
    builds its rule as ``ReturnRule(args.hit_fraction)``."""
    ap.add_argument(
        "--hit-fraction",
        type=float,
        default=default.min_hit_fraction,
        help="averaging scanner's return threshold: share of the footprint that must hit"
        f" (default {default.min_hit_fraction:g}, the rule of this script's published numbers;"
        " 0: any sub-ray, every benchmark's before Dec 6; 0.3: the real SICK LMS200's,"
        " real_geometry.py's default)",
    )


def scene_note(background: str) -> str:
    """The scenario's words for ``background`` (echoed in the benchmarks' JSON)."""
    if background == "none":
        return "trunks only: the breast-height slice"
    return (
        f"ground: scan plane {MOUNT.height} m above the ground, pitched down"
        f" {MOUNT.pitch_deg} deg towards a random heading per vantage; the cloud's own ground"
        f" and understory within {MOUNT.band / 2} m of the beam where it has them (TreeLS"
        " plot, pine, spruce), a ground plane (the cloud's, else flat) with micro-relief"
        " (std 4 cm, 0.3 m correlation: the TreeLS plot's) everywhere"
    )


def dataset_seed(seed: int, name: str) -> int:
    """The seed of slice ``name``'s random stream (vantage points, then the noise draws, and
    its scene): ``seed`` + the slice's position in :data:`~stemmap.eval.real_slices.SLICES`,
    what a run over every slice gives it, so a run over some of them (``--only``) draws the same
    for each."""
    if name not in SLICES:
        raise KeyError(f"unknown slice {name!r}; choose from {', '.join(SLICES)}")
    return seed + list(SLICES).index(name)


def slice_scan_batches(
    ddir: Path,
    n_vantage: int,
    seed: int,
    background: str = "none",
    mount: Mount = MOUNT,
    relief_std: float = RELIEF_STD,
    relief_corr: float = RELIEF_CORR,
    *,
    return_rule: ReturnRule,
) -> Iterator[tuple[str, str, np.ndarray]]:
    """Every slice with reference trunks x :data:`FULL_SCANNERS` configuration: (slice name,
    configuration name ``<model>_<step>deg_noise<cm>cm``, noisy ranges (V, N)), with the
    vantage points, seeds and noise draws of ``real_geometry.run_dataset`` (``seed`` + the
    slice's index; vantage points first, then one noise draw per configuration in order);
    ``return_rule``: the averaging scanner's."""
    for sc in scene_batches(
        ddir, n_vantage, seed, background, mount, relief_std, relief_corr, return_rule=return_rule
    ):
        yield sc.sl.name, sc.config, sc.batch.ranges


@dataclass(frozen=True)
class SceneBatch:
    """One slice x scanner configuration of :func:`scene_batches`: the slice, its vantage
    points, the scanner (model, step deg, range noise m), the hit trunk of every beam of the
    noise-free scans (-1: none) and the noisy scans."""

    sl: RealSlice
    vp: np.ndarray
    model: str
    res: float
    noise: float
    hit: np.ndarray
    batch: ScanBatch
    #: the noise-free ranges (V, N) the noisy ``batch`` was drawn from
    ranges0: np.ndarray | None = None

    @property
    def config(self) -> str:
        return f"{self.model}_{self.res:g}deg_noise{100 * self.noise:g}cm"


def scene_batches(
    ddir: Path,
    n_vantage: int,
    seed: int,
    background: str = "none",
    mount: Mount = MOUNT,
    relief_std: float = RELIEF_STD,
    relief_corr: float = RELIEF_CORR,
    *,
    return_rule: ReturnRule,
    names: Iterable[str] | None = None,
) -> Iterator[SceneBatch]:
    """:func:`slice_scan_batches` with the slice, vantage points, hits and batch of every
    configuration (``names``: only these slices, the others' seeds unchanged;
    ``return_rule``: the averaging scanner's, as ``real_geometry.py --loo`` passes it;
    :data:`ANY_HIT` for the rule of every benchmark before Dec 6)."""
    only = None if names is None else set(names)
    for name in SLICES:
        if only is not None and name not in only:
            continue
        sl = load_slice(ddir, name)
        if not sl.refs:
            continue
        ds = dataset_seed(seed, name)
        rng = np.random.default_rng(ds)
        vp = vantage_points(sl, n_vantage, rng)
        geometry: dict[tuple[str, float], tuple[np.ndarray, np.ndarray]] = {}
        for model, res, noise in FULL_SCANNERS:
            if (model, res) not in geometry:
                geometry[(model, res)] = scene_scans(
                    sl, vp, model, res, background, ds, mount, relief_std, relief_corr,
                    return_rule=return_rule,
                )  # fmt: skip
            ranges0, hit = geometry[(model, res)]
            batch = noisy_batch(ranges0, res, noise, rng)
            yield SceneBatch(sl, vp, model, res, noise, hit, batch, ranges0)
