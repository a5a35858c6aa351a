"""The result of a stem detector on a cloud: :class:`CloudStems` (columnar)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.types import FloatArray, StemObservations

__all__ = ["BASE_SLICE", "BREAST_HEIGHT", "RULE_BH", "CloudStems"]

BREAST_HEIGHT = 1.3
BASE_SLICE = "slice heights as given"  # a pre-cut, height-normalised slice
RULE_BH = "breast height"


# --------------------------------------------------------------------------------------------
# result
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CloudStems:
    """Stems found in one cloud (columnar).

    Attributes
    ----------
    xy : ndarray (K, 2), metres -- stem centre at breast height, cloud frame
    z : ndarray (K,), metres -- z (cloud frame) of the breast-height cross-section
    diameter : ndarray (K,), metres -- DBH
    n_points : ndarray (K,), int -- points supporting the fits
    quality : ndarray (K,), in [0, 1]
    arc_deg : ndarray (K,) -- mean angular coverage of the fitted slices, degrees
    rms : ndarray (K,), metres -- mean residual RMS of the fitted slices
    n_slices : ndarray (K,), int -- slices that passed the quality tests
    taper : ndarray (K,) -- radius change per metre of height (NaN if not estimated)
    height : ndarray (K,), metres -- stem (tree) height, NaN unless requested
    eccentricity : ndarray (K,) -- Munjer's lambda1/lambda2 (NaN for ours)
    diameter_std : ndarray (K,), metres -- 1-sigma of the DBH from the fit covariance (NaN if
        not estimated; see docs/algorithms/cloud.md, Uncertainty)
    xy_cov : ndarray (K, 2, 2), m^2 -- covariance of the stem centre (NaN if not estimated)
    dbh_height : ndarray (K,), metres above the base -- where the DBH was measured
    dbh_rule : ndarray (K,) of str -- why there (``"breast height"``, ``"above buttress"``,
        ...)
    base : str -- what heights are measured from: ``"ground"``, ``"lowest stem points"`` (a
        cloud without ground) or ``"slice heights as given"``
    base_z : float, metres -- z (cloud frame) of the flat base of a cloud without ground (base
        ``"lowest stem points"``: its stem's lowest points); NaN for a ground model or a slice
    method : str
    frame : str
    spacing : float, metres -- point spacing used (measured, or ``StemConfig.spacing``; NaN
        for munjer2025)
    noise_floor : float, metres -- slice-fit noise floor used (median RMS of the plausible
        slice fits, or ``StemConfig.noise_floor``; NaN when not reached or for munjer2025)
    reason : str -- why nothing was found (empty results are falsy)
    """

    xy: FloatArray
    z: FloatArray
    diameter: FloatArray
    n_points: NDArray[np.int64]
    quality: FloatArray
    arc_deg: FloatArray
    rms: FloatArray
    n_slices: NDArray[np.int64]
    taper: FloatArray
    height: FloatArray
    eccentricity: FloatArray
    diameter_std: FloatArray = field(default_factory=lambda: np.zeros(0))
    xy_cov: FloatArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    dbh_height: FloatArray = field(default_factory=lambda: np.zeros(0))
    dbh_rule: NDArray[np.object_] = field(default_factory=lambda: np.zeros(0, dtype=object))
    method: str = ""
    frame: str = "cloud"
    spacing: float = math.nan
    reason: str = ""
    base: str = ""
    noise_floor: float = math.nan
    base_z: float = math.nan

    def __post_init__(self) -> None:
        k = int(self.xy.shape[0])
        # columns added later default to "not estimated" for every row
        if self.diameter_std.shape[0] != k:
            object.__setattr__(self, "diameter_std", np.full(k, np.nan))
        if self.xy_cov.shape[0] != k:
            object.__setattr__(self, "xy_cov", np.full((k, 2, 2), np.nan))
        if self.dbh_height.shape[0] != k:
            object.__setattr__(self, "dbh_height", np.full(k, np.nan))
        if self.dbh_rule.shape[0] != k:
            object.__setattr__(self, "dbh_rule", np.full(k, "", dtype=object))

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def __bool__(self) -> bool:
        """False when no stem was found (``reason`` says why)."""
        return len(self) > 0

    @classmethod
    def empty(
        cls, method: str, frame: str = "cloud", spacing: float = math.nan, *, reason: str = ""
    ) -> CloudStems:
        z = np.zeros(0)
        zi = np.zeros(0, dtype=np.int64)
        return cls(
            np.zeros((0, 2)),
            z,
            z,
            zi,
            z,
            z,
            z,
            zi,
            z,
            z,
            z,
            method=method,
            frame=frame,
            spacing=spacing,
            reason=reason,
        )

    @classmethod
    def from_columns(cls, **cols: Any) -> CloudStems:
        k = np.asarray(cols["xy"]).reshape(-1, 2).shape[0]
        nan = np.full(k, np.nan)
        defaults: dict[str, Any] = {
            "quality": np.ones(k),
            "arc_deg": nan,
            "rms": nan,
            "n_slices": np.ones(k, dtype=np.int64),
            "taper": nan,
            "height": nan,
            "eccentricity": nan,
            "diameter_std": nan,
            "xy_cov": np.full((k, 2, 2), np.nan),
            "dbh_height": nan,
            "dbh_rule": np.full(k, "", dtype=object),
        }
        defaults.update(cols)
        d = defaults
        return cls(
            xy=np.asarray(d["xy"], dtype=np.float64).reshape(-1, 2),
            z=np.asarray(d["z"], dtype=np.float64).reshape(-1),
            diameter=np.asarray(d["diameter"], dtype=np.float64).reshape(-1),
            n_points=np.asarray(d["n_points"], dtype=np.int64).reshape(-1),
            quality=np.asarray(d["quality"], dtype=np.float64).reshape(-1),
            arc_deg=np.asarray(d["arc_deg"], dtype=np.float64).reshape(-1),
            rms=np.asarray(d["rms"], dtype=np.float64).reshape(-1),
            n_slices=np.asarray(d["n_slices"], dtype=np.int64).reshape(-1),
            taper=np.asarray(d["taper"], dtype=np.float64).reshape(-1),
            height=np.asarray(d["height"], dtype=np.float64).reshape(-1),
            eccentricity=np.asarray(d["eccentricity"], dtype=np.float64).reshape(-1),
            diameter_std=np.asarray(d["diameter_std"], dtype=np.float64).reshape(-1),
            xy_cov=np.asarray(d["xy_cov"], dtype=np.float64).reshape(-1, 2, 2),
            dbh_height=np.asarray(d["dbh_height"], dtype=np.float64).reshape(-1),
            dbh_rule=np.asarray(d["dbh_rule"], dtype=object).reshape(-1),
            method=str(d.get("method", "")),
            frame=str(d.get("frame", "cloud")),
            spacing=float(d.get("spacing", math.nan)),
            base=str(d.get("base", "")),
            noise_floor=float(d.get("noise_floor", math.nan)),
            base_z=float(d.get("base_z", math.nan)),
        )

    def select(self, idx: ArrayLike) -> CloudStems:
        i = np.asarray(idx)
        return replace(
            self,
            **{
                k: getattr(self, k)[i]
                for k in (
                    "xy",
                    "z",
                    "diameter",
                    "n_points",
                    "quality",
                    "arc_deg",
                    "rms",
                    "n_slices",
                    "taper",
                    "height",
                    "eccentricity",
                    "diameter_std",
                    "xy_cov",
                    "dbh_height",
                    "dbh_rule",
                )
            },
        )

    def to_observations(self, time: float = 0.0, index: int = 0) -> StemObservations:
        """As a :class:`StemObservations` batch; covariance of (x, y, r) from ``xy_cov`` and
        ``diameter_std`` (x-y and r assumed uncorrelated; NaN where not estimated)."""
        k = len(self)
        covs = np.full((k, 3, 3), np.nan)
        covs[:, :2, :2] = self.xy_cov
        covs[:, :2, 2] = covs[:, 2, :2] = 0.0
        covs[:, 2, 2] = (self.diameter_std / 2) ** 2
        covs[~np.isfinite(covs).all(axis=(1, 2))] = np.nan
        return StemObservations(
            centers=self.xy,
            radii=self.diameter / 2,
            covs=covs,
            n_points=self.n_points,
            arc_deg=self.arc_deg,
            widths=np.full(k, np.nan),
            quality=self.quality,
            index=np.full(k, index, dtype=np.int64),
            times=np.full(k, time),
            source=f"cloud:{self.method}",
            frame=self.frame,
        )
