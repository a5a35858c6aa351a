"""Numba kernel of :class:`stemmap.slam.fastslam.FastSlam` (version 1): one frame's per-particle
candidate selection, maximum-likelihood association and landmark EKF updates.

Kept in its own module so that the compiled kernel (``numba.njit(cache=True)``) is not
invalidated by edits to ``fastslam.py``. The method is described there (Munjer et al. 2025 §3.6;
Montemerlo et al. 2004, unknown data association) and in docs/algorithms/slam-frontends.md.

The kernel is a loop over particles of the *same* floating-point operations, in the same order,
as the numpy path of ``FastSlam`` (``_predict_and_inv``, ``_ekf_update`` and the association
block of ``FastSlam.run``): the numpy arrays (P, K, M) are replaced by scalars, nothing else.
``tests/slam/test_fastslam.py`` checks that both paths give identical trajectories and maps.
Numba compiles without ``fastmath`` (no reassociation, no fused multiply-add), so each
elementary operation rounds as numpy's does.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["associate_update", "compact_inplace", "resample_inplace"]

_C4 = (2 * math.pi) ** 2  # the factor of the Gaussian normaliser log((2 pi)^2 det S)


@numba.njit(cache=True, inline="always")
def _wrap(a: float) -> float:
    """``wrap_angle``: pi - mod(pi - a, 2 pi) (Python/numpy float modulo)."""
    return math.pi - (math.pi - a) % (2.0 * math.pi)


@numba.njit(cache=True, inline="always")
def _inv_innovation(
    t: int,
    hs00: np.ndarray,
    hs01: np.ndarray,
    hs10: np.ndarray,
    hs11: np.ndarray,
    r00: float,
    r11: float,
    i00: np.ndarray,
    i01: np.ndarray,
    i10: np.ndarray,
    i11: np.ndarray,
    lnorm: np.ndarray,
) -> None:
    """``S = H_m Sig H_mᵀ + diag(r00, r11)`` of candidate ``t``: its inverse and
    ``log((2 pi)² det S) / 2`` into slot ``t``."""
    S00 = hs00[t] + r00
    S01 = hs01[t]
    S10 = hs10[t]
    S11 = hs11[t] + r11
    det = S00 * S11 - S01 * S10
    i00[t], i01[t], i10[t], i11[t] = S11 / det, -S01 / det, -S10 / det, S00 / det
    lnorm[t] = 0.5 * math.log(_C4 * det)


@numba.njit(cache=True)
def associate_update(
    X: np.ndarray,
    mu: np.ndarray,
    Sig: np.ndarray,
    nlm: np.ndarray,
    nobs: np.ndarray,
    tlast: np.ndarray,
    dsum: np.ndarray,
    dcnt: np.ndarray,
    r: np.ndarray,
    b: np.ndarray,
    d: np.ndarray,
    off0: float,
    off1: float,
    r00: np.ndarray,
    r11: np.ndarray,
    log_p0: np.ndarray,
    max_cand: int,
    rmax2: float,
    sep2: float,
    tf: float,
    assoc: np.ndarray,
    ll_best: np.ndarray,
) -> None:
    """Associate the frame's detections (r, b, d) (K,) in every particle and update its map.

    Per particle ``p`` (pose ``X[p]``, landmarks ``mu[p, :nlm[p]]``, ``Sig[p, :nlm[p]]``):

    1. candidates: landmarks within ``sqrt(rmax2)`` of the sensor, the ``max_cand`` ones
       closest to any detection mapped with the particle's pose;
    2. log-likelihood of every (detection, candidate) pair,
       ``-d²/2 - log((2 pi)² det S)/2`` with ``S = H_m Sig H_mᵀ + R``; best candidate per
       detection; a match if it is at least ``log_p0``;
    3. a non-match within ``sqrt(sep2)`` of a candidate (``sep2 > 0``) is skipped (-2);
    4. one detection per landmark: the more likely one keeps it (equal: the earlier one), the
       others are skipped (-2);
    5. EKF update of the matched landmarks, observation count, last time, diameter sums.

    ``r00``, ``r11``, ``log_p0`` (K,): each detection's R = diag(r00, r11) and new-landmark
    log-likelihood; when all detections share one R (every entry equal) the innovation
    covariance of a candidate is inverted once, else once per (detection, candidate) pair.

    Fills ``assoc`` (P, K) with the landmark slot, -1 (new landmark) or -2 (skipped), and
    ``ll_best`` (P, K) with the log-likelihood of the matched candidate (-inf when none).
    """
    P = X.shape[0]
    K = r.shape[0]
    cdist = np.empty(max_cand)
    ox = np.empty(K)
    oy = np.empty(K)
    jb = np.empty(K, dtype=np.int64)
    zr = np.empty(max_cand)
    zb = np.empty(max_cand)
    i00 = np.empty(max_cand)
    i01 = np.empty(max_cand)
    i10 = np.empty(max_cand)
    i11 = np.empty(max_cand)
    lnorm = np.empty(max_cand)
    cnd = np.empty(max_cand, dtype=np.int64)
    hs00 = np.empty(max_cand)
    hs01 = np.empty(max_cand)
    hs10 = np.empty(max_cand)
    hs11 = np.empty(max_cand)
    uniform = True
    for k in range(K):
        if r00[k] != r00[0] or r11[k] != r11[0]:
            uniform = False
    for p in range(P):
        px, py, th = X[p, 0], X[p, 1], X[p, 2]
        c, s = math.cos(th), math.sin(th)
        sx = px + off0 * c - off1 * s
        sy = py + off0 * s + off1 * c
        for k in range(K):
            ang = th + b[k]
            ox[k] = sx + r[k] * math.cos(ang)
            oy[k] = sy + r[k] * math.sin(ang)
            assoc[p, k] = -1
            ll_best[p, k] = -np.inf
        # 1. candidates: near the sensor, the max_cand nearest to a detection (kept sorted by
        #    that distance; a bounded insertion instead of a sort of all near landmarks)
        m_n = 0
        for j in range(nlm[p]):
            ddx = mu[p, j, 0] - sx
            ddy = mu[p, j, 1] - sy
            if ddx * ddx + ddy * ddy <= rmax2:
                g = np.inf
                for k in range(K):
                    gx = mu[p, j, 0] - ox[k]
                    gy = mu[p, j, 1] - oy[k]
                    gx = gx * gx + gy * gy
                    if gx < g:
                        g = gx
                if m_n == max_cand:
                    if not g < cdist[m_n - 1]:
                        continue
                    t = m_n - 1
                else:
                    t = m_n
                    m_n += 1
                while t > 0 and g < cdist[t - 1]:
                    cdist[t] = cdist[t - 1]
                    cnd[t] = cnd[t - 1]
                    t -= 1
                cdist[t] = g
                cnd[t] = j
        if m_n == 0:
            continue
        # 2. predicted measurement and inverse innovation covariance per candidate
        for t in range(m_n):
            j = cnd[t]
            dx = mu[p, j, 0] - (px + off0 * c - off1 * s)
            dy = mu[p, j, 1] - (py + off0 * s + off1 * c)
            q = max(dx * dx + dy * dy, 1e-12)
            rr = math.sqrt(q)
            zr[t] = rr
            zb[t] = _wrap(math.atan2(dy, dx) - th)
            h00, h01, h10, h11 = dx / rr, dy / rr, -dy / q, dx / q
            s00, s01, s10, s11 = Sig[p, j, 0, 0], Sig[p, j, 0, 1], Sig[p, j, 1, 0], Sig[p, j, 1, 1]
            a00 = h00 * s00 + h01 * s10
            a01 = h00 * s01 + h01 * s11
            a10 = h10 * s00 + h11 * s10
            a11 = h10 * s01 + h11 * s11
            hs00[t] = a00 * h00 + a01 * h01
            hs01[t] = a00 * h10 + a01 * h11
            hs10[t] = a10 * h00 + a11 * h01
            hs11[t] = a10 * h10 + a11 * h11
            if uniform:
                _inv_innovation(
                    t, hs00, hs01, hs10, hs11, r00[0], r11[0], i00, i01, i10, i11, lnorm
                )
        for k in range(K):
            best = -np.inf
            jbest = -1
            if not uniform:
                for t in range(m_n):
                    _inv_innovation(
                        t, hs00, hs01, hs10, hs11, r00[k], r11[k], i00, i01, i10, i11, lnorm
                    )
            for t in range(m_n):
                nu0 = r[k] - zr[t]
                nu1 = _wrap(b[k] - zb[t])
                d2 = nu0 * i00[t] * nu0
                d2 += nu0 * i01[t] * nu1
                d2 += nu1 * i10[t] * nu0
                d2 += nu1 * i11[t] * nu1
                ll = -0.5 * d2
                ll -= lnorm[t]
                if ll > best:
                    best = ll
                    jbest = t
            if jbest >= 0 and best >= log_p0[k]:
                jb[k] = cnd[jbest]
                ll_best[p, k] = best
            else:
                jb[k] = -1
                # 3. an unmatched detection close to a landmark: ambiguous, skipped
                if sep2 > 0:
                    for t in range(m_n):
                        ex = mu[p, cnd[t], 0] - ox[k]
                        ey = mu[p, cnd[t], 1] - oy[k]
                        if ex * ex + ey * ey < sep2:
                            assoc[p, k] = -2
                            break
        # 4. one detection per landmark
        for k in range(K):
            if jb[k] < 0:
                continue
            win = True
            lk = ll_best[p, k]
            for k2 in range(K):
                l2 = ll_best[p, k2]
                if k2 != k and jb[k2] == jb[k] and (l2 > lk or (l2 == lk and k2 < k)):
                    win = False
                    break
            assoc[p, k] = jb[k] if win else -2
        # 5. EKF update of the winners (distinct landmarks): _fastslam_particles._ekf_update
        for k in range(K):
            j = assoc[p, k]
            if j < 0:
                continue
            m0, m1 = mu[p, j, 0], mu[p, j, 1]
            dx = m0 - (px + off0 * c - off1 * s)
            dy = m1 - (py + off0 * s + off1 * c)
            q = max(dx * dx + dy * dy, 1e-12)
            rr = math.sqrt(q)
            zbk = _wrap(math.atan2(dy, dx) - th)
            h00, h01, h10, h11 = dx / rr, dy / rr, -dy / q, dx / q
            n0 = r[k] - rr
            n1 = _wrap(b[k] - zbk)
            s00, s01, s10, s11 = Sig[p, j, 0, 0], Sig[p, j, 0, 1], Sig[p, j, 1, 0], Sig[p, j, 1, 1]
            t00 = h00 * s00 + h01 * s10
            t01 = h00 * s01 + h01 * s11
            t10 = h10 * s00 + h11 * s10
            t11 = h10 * s01 + h11 * s11
            S00 = t00 * h00 + t01 * h01 + r00[k]
            S01 = t00 * h10 + t01 * h11 + 0.0
            S10 = t10 * h00 + t11 * h01 + 0.0
            S11 = t10 * h10 + t11 * h11 + r11[k]
            det = S00 * S11 - S01 * S10
            j00, j01, j10, j11 = S11 / det, -S01 / det, -S10 / det, S00 / det
            u00 = s00 * h00 + s01 * h01
            u01 = s00 * h10 + s01 * h11
            u10 = s10 * h00 + s11 * h01
            u11 = s10 * h10 + s11 * h11
            k00 = u00 * j00 + u01 * j10
            k01 = u00 * j01 + u01 * j11
            k10 = u10 * j00 + u11 * j10
            k11 = u10 * j01 + u11 * j11
            mu[p, j, 0] = m0 + (k00 * n0 + k01 * n1)
            mu[p, j, 1] = m1 + (k10 * n0 + k11 * n1)
            w00 = 1.0 - (k00 * h00 + k01 * h10)
            w01 = 0.0 - (k00 * h01 + k01 * h11)
            w10 = 0.0 - (k10 * h00 + k11 * h10)
            w11 = 1.0 - (k10 * h01 + k11 * h11)
            v01 = w00 * s01 + w01 * s11
            v10 = w10 * s00 + w11 * s10
            Sig[p, j, 0, 0] = 0.5 * ((w00 * s00 + w01 * s10) * 2.0)
            Sig[p, j, 1, 1] = 0.5 * ((w10 * s01 + w11 * s11) * 2.0)
            Sig[p, j, 0, 1] = 0.5 * (v01 + v10)
            Sig[p, j, 1, 0] = 0.5 * (v10 + v01)
            nobs[p, j] += 1
            tlast[p, j] = tf
            if math.isfinite(d[k]):
                dsum[p, j] += d[k]
                dcnt[p, j] += 1


@numba.njit(cache=True, inline="always")
def _copy_slot(
    q: int,
    i: int,
    p: int,
    j: int,
    mu: np.ndarray,
    Sig: np.ndarray,
    nobs: np.ndarray,
    dsum: np.ndarray,
    dcnt: np.ndarray,
    tfirst: np.ndarray,
    tlast: np.ndarray,
) -> None:
    """Landmark ``i`` of particle ``q`` -> landmark ``j`` of particle ``p`` (element by element:
    a slice assignment within one array would go through a temporary copy)."""
    mu[p, j, 0] = mu[q, i, 0]
    mu[p, j, 1] = mu[q, i, 1]
    Sig[p, j, 0, 0] = Sig[q, i, 0, 0]
    Sig[p, j, 0, 1] = Sig[q, i, 0, 1]
    Sig[p, j, 1, 0] = Sig[q, i, 1, 0]
    Sig[p, j, 1, 1] = Sig[q, i, 1, 1]
    nobs[p, j] = nobs[q, i]
    dsum[p, j] = dsum[q, i]
    dcnt[p, j] = dcnt[q, i]
    tfirst[p, j] = tfirst[q, i]
    tlast[p, j] = tlast[q, i]


@numba.njit(cache=True)
def resample_inplace(
    idx: np.ndarray,
    nlm: np.ndarray,
    mu: np.ndarray,
    Sig: np.ndarray,
    nobs: np.ndarray,
    dsum: np.ndarray,
    dcnt: np.ndarray,
    tfirst: np.ndarray,
    tlast: np.ndarray,
) -> None:
    """Particle ``p`` becomes a copy of particle ``idx[p]`` (``idx`` non-decreasing, as
    systematic resampling returns it), in place, copying only the landmarks in use.

    With ``idx`` non-decreasing, the particles with ``idx[p] > p`` read sources that are either
    unchanged (``idx[q] == q``) or not yet overwritten when visited in ascending order, and those
    with ``idx[p] < p`` likewise in descending order; so no copy of the whole map is needed.
    """
    P = idx.shape[0]
    for p in range(P):  # copy from above, ascending
        q = idx[p]
        if q > p:
            for j in range(nlm[q]):
                _copy_slot(q, j, p, j, mu, Sig, nobs, dsum, dcnt, tfirst, tlast)
            nlm[p] = nlm[q]
    for p in range(P - 1, -1, -1):  # copy from below, descending
        q = idx[p]
        if q < p:
            for j in range(nlm[q]):
                _copy_slot(q, j, p, j, mu, Sig, nobs, dsum, dcnt, tfirst, tlast)
            nlm[p] = nlm[q]


@numba.njit(cache=True)
def compact_inplace(
    keep: np.ndarray,
    nlm: np.ndarray,
    mu: np.ndarray,
    Sig: np.ndarray,
    nobs: np.ndarray,
    dsum: np.ndarray,
    dcnt: np.ndarray,
    tfirst: np.ndarray,
    tlast: np.ndarray,
) -> None:
    """Delete the landmarks with ``keep[p, j]`` False (``j < nlm[p]``) from every particle,
    in place, keeping the order of the others; ``nlm`` becomes the number kept."""
    for p in range(nlm.shape[0]):
        w = 0
        for j in range(nlm[p]):
            if keep[p, j]:
                if w != j:
                    _copy_slot(p, j, p, w, mu, Sig, nobs, dsum, dcnt, tfirst, tlast)
                w += 1
        nlm[p] = w
