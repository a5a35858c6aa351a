"""The range-noise floor read from the outlines of the batch (ours, issue 11, Dec 6;
``outline_floor_points``, off by default).

The ``stemmap`` preset's ``sigma`` (1 cm) is a floor under every candidate's range noise:
``sigma_from_scan`` raises it to a scan's measured noise, never lowers it. The floor stands for
what the measured range noise does not hold -- a real outline's departure from its fitted
circle (bark, an ellipse) -- and on real bark it holds the fits together (lidR: at a 3 mm
floor 0.07-0.12 of the views within 3 cm lost; docs/algorithms/scan-detection.md, "The two
FORTLS rows left against textbook Kasa", part 5). On a perfect circle it is far too large:
the fit of a 4-5-return arc weighs its ranges at 1 cm and the tangent prior decides the
radius (the same section, part 2). A 4-5-return candidate cannot show its own outline (its
fit has 1-2 degrees of freedom: "A mixed return beyond the end", part 1 (b)); the
well-sampled trunks of the same scans can.

:func:`batch_outline` pools the residuals of the interior returns (every return but the two
ends: an averaging scanner's edge returns are partial footprints, a first-echo one's the
silhouette) of every candidate of the batch that passed its fit tests with at least
``outline_floor_points`` returns, each scaled by ``sqrt(n / (n - 3))`` (a fit of ``n`` returns
leaves residuals of ``(n - 3) / n`` the variance), and takes their biweight scale
(:func:`~stemmap.scan.plausibility.biweight_scale`: centred on their median, so the common
offset an averaging footprint gives on a curved surface drops out; robust to a branch stub or
a bark flake). Less the batch's measured range noise in quadrature, that is the outline term.
The same rules as the batch's noise estimate (:func:`~stemmap.scan.plausibility.scan_noise`):
at least :data:`~stemmap.scan.plausibility.SCAN_NOISE_MIN_TRIPLES` residuals, and no one
candidate holding more than half of them (the median's breakdown point: one trunk does not
decide the batch's outline).

:func:`scan_floors` puts it in place of ``sigma`` as every scan's floor:
``min(sigma, max(outline_floor_min, sqrt(noise^2 + outline^2)))`` with ``noise`` the scan's
measured range noise, at least the batch's (the median over the pooled candidates' scans that
have an estimate), so a scan without an estimate of its own (a sparse scan: too few interior
triples) takes the pooled scale itself, the batch's noise and the outline together (a
noise-free floor on a noisy sparse scan breaks its fits: the same section, part 3).
``sigma_from_scan`` still raises the floor to the scan's noise. Capped
at ``sigma``: the option only lowers the assumed floor where the batch's outlines are smoother
than it assumes. Where the batch has no estimate every scan keeps ``sigma``.

The batch is the scans detected together (one ``detect`` call, or one chunk of at most
``chunk_scans`` scans of ``detect_batch``), as for the batch's noise estimate.

The detector reads the floor in a first pass (candidates, fits and fit tests at ``sigma``) and
then runs the whole pipeline with it (:meth:`~stemmap.scan.detect.ScanTrunkDetector._run_numpy`;
numpy path, the compiled kernel does not implement it).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.scan.plausibility import SCAN_NOISE_MIN_TRIPLES, biweight_scale
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig

__all__ = ["batch_noise", "batch_outline", "interior_residuals", "outline_floor_on", "scan_floors"]


def outline_floor_on(cfg: DetectorConfig) -> bool:
    """Whether ``outline_floor_points`` acts: set, with a ``sigma`` floor to replace, and no
    first-echo footprint correction (``beam_footprint_deg`` 0). A first-echo fit has its own
    floor read from the data, ``fit_noise_floor`` (the measured noise and the footprint's
    range step / sqrt(12), per candidate): the step a far 4-return arc carries is centimetres,
    which the interior residuals of the near well-sampled trunks do not show; on the
    real-geometry LOO the option lowered the nearest-return training score in every fold
    (docs/algorithms/scan-detection.md, "The outline floor read from the batch")."""
    return cfg.outline_floor_points > 0 and cfg.sigma > 0 and cfg.beam_footprint_deg == 0


def interior_residuals(
    segs: Segments, centers: FloatArray, radii: FloatArray
) -> tuple[FloatArray, NDArray[np.int64]]:
    """The residuals ``|p - c| - R`` of every return of ``segs`` but each segment's two end
    returns, scaled by ``sqrt(n / (n - 3))`` (``n``: the segment's returns), and the segment
    each belongs to. Segments of fewer than 4 returns give none."""
    p = segs.points
    lab = segs.labels
    n = segs.counts.astype(np.float64)
    res = np.hypot(p.x - centers[lab, 0], p.y - centers[lab, 1]) - radii[lab]
    idx = np.arange(len(p))
    inner = (idx > segs.start[lab]) & (idx < segs.stop[lab] - 1) & (n[lab] > 3.0)
    scale = np.sqrt(n / np.maximum(n - 3.0, 1.0))
    out: FloatArray = res[inner] * scale[lab[inner]]
    return out, lab[inner]


def batch_outline(
    segs: Segments,
    centers: FloatArray,
    radii: FloatArray,
    passed: NDArray[np.bool_],
    least: int,
) -> tuple[float, float, float]:
    """The batch's outline term, the pooled residual scale it came from and the batch's
    measured range noise taken out of it (:func:`batch_noise`), metres (module docstring);
    NaN where the batch has no estimate. ``segs``: the
    candidates; ``centers`` / ``radii``: their fits; ``passed``: the fit converged and passed
    the fit tests; ``least``: the fewest returns of a candidate that joins the pool."""
    keep = passed & (segs.counts >= least) & np.isfinite(radii)
    if not np.any(keep):
        return math.nan, math.nan, math.nan
    sub = segs.select(keep)
    u, lab = interior_residuals(sub, centers[keep], radii[keep])
    u_ok = np.isfinite(u)
    u, lab = u[u_ok], lab[u_ok]
    if u.shape[0] < SCAN_NOISE_MIN_TRIPLES:
        return math.nan, math.nan, math.nan
    if 2 * int(np.bincount(lab).max()) > u.shape[0]:
        return math.nan, math.nan, math.nan  # one candidate holds more than half
    s = biweight_scale(u)
    nb = batch_noise(sub.points.noise, sub.scan)
    return math.sqrt(max(s * s - nb * nb, 0.0)), s, nb


def batch_noise(noise: FloatArray | None, scans: NDArray[np.int64]) -> float:
    """The median measured range noise of the scans ``scans`` (one entry per candidate) that
    have an estimate (finite and > 0: :func:`~stemmap.scan.plausibility.scan_noise` gives 0
    or NaN where a scan has none), 0 where none has."""
    if noise is None:
        return 0.0
    per = noise[scans]
    per = per[np.isfinite(per) & (per > 0)]
    return float(np.median(per)) if per.size else 0.0


def scan_floors(
    cfg: DetectorConfig, outline: float, batch: float, noise: FloatArray | None, n_scans: int
) -> FloatArray:
    """Every scan's floor in place of ``sigma`` (module docstring), ``sigma`` where
    ``outline`` is NaN (no estimate): ``sqrt(n^2 + outline^2)`` clipped to
    ``[outline_floor_min, sigma]``, ``n`` the scan's measured range noise ``noise`` (None,
    NaN or 0: none) but at least the ``batch``'s (:func:`batch_noise`; the range noise is the
    sensor's, and a scan's estimate below the batch's is as often a scan whose second
    differences missed part of the bark the pooled residuals hold)."""
    if not math.isfinite(outline):
        return np.full(n_scans, cfg.sigma)
    n = np.full(n_scans, batch)
    if noise is not None:
        meas = np.asarray(noise, dtype=np.float64)
        n = np.fmax(n, np.where(np.isfinite(meas), meas, 0.0))
    out: FloatArray = np.minimum(cfg.sigma, np.maximum(cfg.outline_floor_min, np.hypot(n, outline)))
    return out
