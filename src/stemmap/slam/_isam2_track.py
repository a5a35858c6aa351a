"""Numba kernels of :class:`stemmap.slam.graph.Isam2Slam`: pose tracking and association,
the per-window measurement merge, and the banded solve of the tree marginals.

Kept in its own module so that the compiled kernels (``numba.njit(cache=True)``) are not
invalidated by edits to ``graph.py``. The method is described in ``graph.py`` and in
docs/algorithms/slam.md ("Front-end").
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = [
    "C_AMBIG",
    "C_FAR",
    "C_LOCAL",
    "C_NEW",
    "C_REACQ",
    "C_SINGLE",
    "band_cho_solve",
    "grow_landmarks",
    "merge_window",
    "track_keyframe",
]

# ---------------------------------------------------------------------------------------------
# Front-end tracker (numba): pose tracking against the current tree estimates + association
# ---------------------------------------------------------------------------------------------

# indices into the per-run counters array filled by _track_keyframe
C_LOCAL, C_REACQ, C_SINGLE, C_NEW, C_AMBIG, C_FAR = range(6)


@numba.njit(cache=True)
def _inv2(a: float, b: float, c: float) -> tuple[float, float, float, float]:
    """Inverse of the symmetric 2x2 [[a, b], [b, c]] as (ia, ib, ic, det)."""
    det = a * c - b * b
    return c / det, -b / det, a / det, det


@numba.njit(cache=True)
def track_keyframe(
    f_start: int,
    f_stop: int,
    kf_frame: int,
    f_upd: int,
    ptr: np.ndarray,
    rng: np.ndarray,
    brg: np.ndarray,
    dia: np.ndarray,
    sp_dr: np.ndarray,
    cov_f: np.ndarray,
    cum_xy: np.ndarray,
    cum_th: np.ndarray,
    cum_dist: np.ndarray,
    trk: np.ndarray,
    P: np.ndarray,
    fc: np.ndarray,
    lm_xy: np.ndarray,
    lm_dsum: np.ndarray,
    lm_dn: np.ndarray,
    lm_nobs: np.ndarray,
    lm_first: np.ndarray,
    lm_last: np.ndarray,
    lm_inc: np.ndarray,
    n_lm_in: int,
    params: np.ndarray,
    out_j: np.ndarray,
    out_kx: np.ndarray,
    out_ky: np.ndarray,
    out_wxy: np.ndarray,
    out_wth: np.ndarray,
    counters: np.ndarray,
) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Track the sensor pose through frames [f_start, f_stop) of one keyframe and associate.

    Steps (module docs of :mod:`stemmap.slam.graph`): propagate ``trk``/``P`` from frame
    ``fc[0]`` with the dead-reckoned sensor increments (``sp_dr``) and their tangent covariances
    (``cov_f``); associate each frame's detections with the local trees and update the tracked
    pose (two passes); re-acquire the other trees as a consistent group; start new trees.

    In/out: ``trk`` (3,) tracked sensor pose at frame ``fc[0]``, ``P`` (3, 3) its covariance
    (world frame, heading error about the sensor), the landmark arrays (grown by the caller:
    room for every detection of the keyframe), ``counters``. ``f_upd`` is the first frame of the
    keyframe of the last iSAM2 update; ``lm_inc[j]`` the last frame of tree ``j`` whose
    observation is in iSAM2 (-1: none yet). Scratch per associated detection (``out_*``,
    room for every detection of the keyframe): tree, position in the keyframe's sensor frame
    ``kf_frame`` (dead reckoning within the window) and the window's odometry variances; they
    are merged per tree by :func:`merge_window` (called here: one compiled function to load
    per process instead of two, ~0.07 s). ``params``: vr, vb, sd2, use_diameter, gate,
    new_chi2, new_min_dist, max_range, max_drift², local_drift², consensus_chi2, drift_scale,
    min_window_obs.

    Returns ``(n_lm, n_out, *merge_window(...))``: the number of trees, of associated
    detections (in ``out_*``), then the window's measurements (trees, bearing, range, sigmas,
    number of trees skipped).
    """
    vr, vb, sd2, use_d = params[0], params[1], params[2], params[3] > 0.5
    gate, new_chi2, new_min_dist, max_range = params[4], params[5], params[6], params[7]
    max_drift2, local_drift2, cons_gate = params[8], params[9], params[10]
    drift_scale = params[11]
    n_lm = n_lm_in
    n_out = 0
    for f in range(f_start, f_stop):
        # ---- 1. propagate the tracked pose and its 3x3 covariance from frame fc to f
        g = fc[0]
        while g < f:
            a0, b0 = sp_dr[g], sp_dr[g + 1]
            c0, s0 = math.cos(a0[2]), math.sin(a0[2])
            dx, dy = b0[0] - a0[0], b0[1] - a0[1]
            lx, ly = c0 * dx + s0 * dy, -s0 * dx + c0 * dy
            lt = (b0[2] - a0[2] + math.pi) % (2.0 * math.pi) - math.pi
            ct, st = math.cos(trk[2]), math.sin(trk[2])
            nx = trk[0] + ct * lx - st * ly
            ny = trk[1] + st * lx + ct * ly
            nt = trk[2] + lt
            # error propagation: position error + heading error swept over the chord
            F = np.eye(3)
            F[0, 2] = -(ny - trk[1])
            F[1, 2] = nx - trk[0]
            Pn = F @ P @ F.T
            # increment noise (sensor tangent, end frame) rotated to the world
            c1, s1 = math.cos(nt), math.sin(nt)
            Rz = np.eye(3)
            Rz[0, 0], Rz[0, 1], Rz[1, 0], Rz[1, 1] = c1, -s1, s1, c1
            Pn += Rz @ cov_f[g] @ Rz.T
            P[:, :] = Pn
            trk[0], trk[1], trk[2] = nx, ny, nt
            g += 1
        fc[0] = f
        # ---- 2. detections of frame f (within max_range), world positions and covariances
        i0, i1 = ptr[f], ptr[f + 1]
        nd = 0
        for i in range(i0, i1):
            if rng[i] <= max_range:
                nd += 1
            else:
                counters[C_FAR] += 1
        if nd == 0:
            continue
        r = np.empty(nd)
        b = np.empty(nd)
        dd = np.empty(nd)
        q = 0
        for i in range(i0, i1):
            if rng[i] <= max_range:
                r[q], b[q], dd[q] = rng[i], brg[i], dia[i]
                q += 1
        # meas world covariance (bearing + range noise), per detection
        mxx = np.empty(nd)
        mxy = np.empty(nd)
        myy = np.empty(nd)
        wx = np.empty(nd)
        wy = np.empty(nd)
        px0, py0, pt0 = trk[0], trk[1], trk[2]
        P0 = P.copy()
        for i in range(nd):
            ang = pt0 + b[i]
            ca, sa = math.cos(ang), math.sin(ang)
            wx[i] = px0 + r[i] * ca
            wy[i] = py0 + r[i] * sa
            mxx[i] = ca * ca * vr + (r[i] * sa) ** 2 * vb
            myy[i] = sa * sa * vr + (r[i] * ca) ** 2 * vb
            mxy[i] = ca * sa * vr - r[i] * r[i] * sa * ca * vb
        # near trees, their variance and drift relative to the estimate at the last update
        near_cnt = 0
        lim = (max_range + 10.0) ** 2
        for j in range(n_lm):
            ex, ey = lm_xy[j, 0] - px0, lm_xy[j, 1] - py0
            if ex * ex + ey * ey < lim:
                near_cnt += 1
        near = np.empty(near_cnt, dtype=np.int64)
        tvar = np.empty(near_cnt)
        drift = np.empty(near_cnt)
        hdrift = np.empty(near_cnt)
        dmean = np.empty(near_cnt)
        dvar = np.empty(near_cnt)
        q = 0
        for j in range(n_lm):
            ex, ey = lm_xy[j, 0] - px0, lm_xy[j, 1] - py0
            if ex * ex + ey * ey < lim:
                near[q] = j
                tvar[q] = (vr + 400.0 * vb) / max(lm_nobs[j], 1)
                f0 = lm_inc[j]
                if f0 < 0 or f0 >= f_upd:
                    drift[q] = 0.0
                    hdrift[q] = 0.0
                else:
                    dD = cum_dist[f_upd] - cum_dist[f0]
                    hv = cum_th[f_upd] - cum_th[f0]
                    rr2 = ex * ex + ey * ey
                    drift[q] = min(
                        drift_scale * ((cum_xy[f_upd] - cum_xy[f0]) + hv * (dD * dD / 3.0 + rr2)),
                        max_drift2,
                    )
                    hdrift[q] = hv
                n_d = max(lm_dn[j], 1)
                dmean[q] = lm_dsum[j] / n_d
                dvar[q] = sd2 + sd2 / n_d
                q += 1
        assign = np.full(nd, -1, dtype=np.int64)
        tree_used = np.zeros(near_cnt, dtype=np.bool_)
        # ---- 3. local association + pose update (two passes: gate with the prior, update,
        # re-gate with the posterior); only trees whose estimate is tied to the local map
        ncap = nd * near_cnt
        cand_i = np.empty(ncap, dtype=np.int64)
        cand_q = np.empty(ncap, dtype=np.int64)
        cand_n = np.empty(ncap)
        for _it in range(2):
            n_c = 0
            for i in range(nd):
                for qq in range(near_cnt):
                    if drift[qq] > local_drift2:
                        continue
                    j = near[qq]
                    ex = lm_xy[j, 0] - wx[i]
                    ey = lm_xy[j, 1] - wy[i]
                    # J P J^T with J = [[1, 0, -(wy - py)], [0, 1, wx - px]]
                    jx, jy = -(wy[i] - trk[1]), wx[i] - trk[0]
                    sxx = P[0, 0] + 2 * jx * P[0, 2] + jx * jx * P[2, 2]
                    syy = P[1, 1] + 2 * jy * P[1, 2] + jy * jy * P[2, 2]
                    sxy = P[0, 1] + jx * P[1, 2] + jy * P[0, 2] + jx * jy * P[2, 2]
                    lv = tvar[qq] + drift[qq]
                    sxx += mxx[i] + lv
                    syy += myy[i] + lv
                    sxy += mxy[i]
                    ia, ib, ic, det = _inv2(sxx, sxy, syy)
                    d2 = ia * ex * ex + 2 * ib * ex * ey + ic * ey * ey
                    if use_d and math.isfinite(dd[i]) and math.isfinite(dmean[qq]):
                        d2 += (dd[i] - dmean[qq]) ** 2 / dvar[qq]
                    if d2 < gate:
                        cand_i[n_c] = i
                        cand_q[n_c] = qq
                        cand_n[n_c] = d2 + math.log(det)
                        n_c += 1
            # greedy one-to-one by negative log-likelihood
            for i in range(nd):
                assign[i] = -1
            tree_used[:] = False
            if n_c:
                order = np.argsort(cand_n[:n_c])
                for t in order:
                    i, qq = cand_i[t], cand_q[t]
                    if assign[i] >= 0 or tree_used[qq]:
                        continue
                    assign[i] = qq
                    tree_used[qq] = True
            # MAP pose correction from the prior (trk at pass 0 = px0, py0, pt0; P0) with the
            # matched trees treated as known points of covariance (tvar + drift) I
            Lam = np.linalg.inv(P0)
            eta = np.zeros(3)
            n_m = 0
            for i in range(nd):
                qq = assign[i]
                if qq < 0:
                    continue
                n_m += 1
                j = near[qq]
                ang = pt0 + b[i]
                ca, sa = math.cos(ang), math.sin(ang)
                ox, oy = px0 + r[i] * ca, py0 + r[i] * sa
                ex, ey = lm_xy[j, 0] - ox, lm_xy[j, 1] - oy
                lv = tvar[qq] + drift[qq]
                ia, ib, ic, det = _inv2(mxx[i] + lv, mxy[i], myy[i] + lv)
                jx, jy = -(oy - py0), ox - px0
                # H = [[1, 0, jx], [0, 1, jy]]; Lam += H^T W H; eta += H^T W e
                Hm = np.zeros((2, 3))
                Hm[0, 0], Hm[0, 2], Hm[1, 1], Hm[1, 2] = 1.0, jx, 1.0, jy
                W = np.empty((2, 2))
                W[0, 0], W[0, 1], W[1, 0], W[1, 1] = ia, ib, ib, ic
                Lam += Hm.T @ W @ Hm
                ev = np.empty(2)
                ev[0], ev[1] = ex, ey
                eta += Hm.T @ (W @ ev)
            if n_m == 0:
                trk[0], trk[1], trk[2] = px0, py0, pt0
                P[:, :] = P0
                break
            Pp = np.linalg.inv(Lam)
            dl = Pp @ eta
            trk[0], trk[1], trk[2] = px0 + dl[0], py0 + dl[1], pt0 + dl[2]
            P[:, :] = 0.5 * (Pp + Pp.T)
            for i in range(nd):
                ang = trk[2] + b[i]
                wx[i] = trk[0] + r[i] * math.cos(ang)
                wy[i] = trk[1] + r[i] * math.sin(ang)
        for i in range(nd):
            if assign[i] >= 0:
                counters[C_LOCAL] += 1
        # ---- 4. re-acquisition of trees not tied to the local map (loop closures): wide gate
        # with their drift, accepted only as a group with a common offset (>= 2 detections),
        # or singly if the tree is where the tracked pose puts it (tight gate, no drift)
        ci = np.empty(ncap, dtype=np.int64)
        cq = np.empty(ncap, dtype=np.int64)
        cex = np.empty(ncap)
        cey = np.empty(ncap)
        cvar = np.empty(ncap)
        cn = np.empty(ncap)
        ctight = np.empty(ncap, dtype=np.bool_)
        nc = 0
        for i in range(nd):
            if assign[i] >= 0:
                continue
            for qq in range(near_cnt):
                if tree_used[qq] or drift[qq] <= local_drift2:
                    continue
                j = near[qq]
                ex = lm_xy[j, 0] - wx[i]
                ey = lm_xy[j, 1] - wy[i]
                jx, jy = -(wy[i] - trk[1]), wx[i] - trk[0]
                sxx = P[0, 0] + 2 * jx * P[0, 2] + jx * jx * P[2, 2] + mxx[i] + tvar[qq]
                syy = P[1, 1] + 2 * jy * P[1, 2] + jy * jy * P[2, 2] + myy[i] + tvar[qq]
                sxy = P[0, 1] + jx * P[1, 2] + jy * P[0, 2] + jx * jy * P[2, 2] + mxy[i]
                extra = 0.0
                if use_d and math.isfinite(dd[i]) and math.isfinite(dmean[qq]):
                    extra = (dd[i] - dmean[qq]) ** 2 / dvar[qq]
                ia, ib, ic, det = _inv2(sxx, sxy, syy)
                d2t = ia * ex * ex + 2 * ib * ex * ey + ic * ey * ey + extra
                ia, ib, ic, det = _inv2(sxx + drift[qq], sxy, syy + drift[qq])
                d2 = ia * ex * ex + 2 * ib * ex * ey + ic * ey * ey + extra
                if d2 < gate:
                    ci[nc] = i
                    cq[nc] = qq
                    cex[nc] = ex
                    cey[nc] = ey
                    cvar[nc] = 0.5 * (sxx + syy)
                    cn[nc] = d2 + math.log(det)
                    ctight[nc] = d2t < gate
                    nc += 1
        if nc:
            support = np.zeros(nc, dtype=np.int64)
            for p in range(nc):
                for p2 in range(nc):
                    if ci[p2] == ci[p] or cq[p2] == cq[p]:
                        continue
                    jp, jq = near[cq[p]], near[cq[p2]]
                    sep2 = (lm_xy[jp, 0] - lm_xy[jq, 0]) ** 2 + (lm_xy[jp, 1] - lm_xy[jq, 1]) ** 2
                    hv = min(hdrift[cq[p]], hdrift[cq[p2]])
                    tol = cvar[p] + cvar[p2] + 0.05**2 + hv * sep2
                    de2 = (cex[p] - cex[p2]) ** 2 + (cey[p] - cey[p2]) ** 2
                    if de2 < cons_gate * tol:
                        support[p] += 1
            best = -1
            for p in range(nc):
                if support[p] >= 1 and (
                    best < 0
                    or support[p] > support[best]
                    or (support[p] == support[best] and cn[p] < cn[best])
                ):
                    best = p
            if best >= 0:
                # the seed and the pairs consistent with it, one-to-one by closeness
                assign[ci[best]] = cq[best]
                tree_used[cq[best]] = True
                counters[C_REACQ] += 1
                dev = np.empty(nc)
                for p2 in range(nc):
                    dev[p2] = (cex[best] - cex[p2]) ** 2 + (cey[best] - cey[p2]) ** 2
                for p2 in np.argsort(dev):
                    i, qq = ci[p2], cq[p2]
                    if assign[i] >= 0 or tree_used[qq]:
                        continue
                    jp, jq = near[cq[best]], near[qq]
                    sep2 = (lm_xy[jp, 0] - lm_xy[jq, 0]) ** 2 + (lm_xy[jp, 1] - lm_xy[jq, 1]) ** 2
                    hv = min(hdrift[cq[best]], hdrift[qq])
                    tol = cvar[best] + cvar[p2] + 0.05**2 + hv * sep2
                    if dev[p2] < cons_gate * tol:
                        assign[i] = qq
                        tree_used[qq] = True
                        counters[C_REACQ] += 1
            # single pairs where the tree is where the tracked pose says (tight gate)
            order = np.argsort(cn[:nc])
            for p in order:
                i, qq = ci[p], cq[p]
                if assign[i] >= 0 or tree_used[qq] or not ctight[p]:
                    continue
                assign[i] = qq
                tree_used[qq] = True
                counters[C_SINGLE] += 1
        # ---- 5. unmatched detections: new tree if clearly separate, else discard
        kx0, ky0, kt0 = sp_dr[kf_frame, 0], sp_dr[kf_frame, 1], sp_dr[kf_frame, 2]
        ck, sk = math.cos(kt0), math.sin(kt0)
        fx, fy, ft = sp_dr[f, 0], sp_dr[f, 1], sp_dr[f, 2]
        qx = ck * (fx - kx0) + sk * (fy - ky0)
        qy = -sk * (fx - kx0) + ck * (fy - ky0)
        qt = ft - kt0
        cq_, sq_ = math.cos(qt), math.sin(qt)
        w_xy = cum_xy[f] - cum_xy[kf_frame]
        w_th = cum_th[f] - cum_th[kf_frame]
        for i in range(nd):
            if assign[i] >= 0:
                j = near[assign[i]]
            else:
                sep = True
                for qq in range(near_cnt):
                    jn = near[qq]
                    ex = lm_xy[jn, 0] - wx[i]
                    ey = lm_xy[jn, 1] - wy[i]
                    if ex * ex + ey * ey < new_min_dist * new_min_dist:
                        sep = False
                        break
                    jx, jy = -(wy[i] - trk[1]), wx[i] - trk[0]
                    lv = tvar[qq] + drift[qq]
                    sxx = P[0, 0] + 2 * jx * P[0, 2] + jx * jx * P[2, 2] + mxx[i] + lv
                    syy = P[1, 1] + 2 * jy * P[1, 2] + jy * jy * P[2, 2] + myy[i] + lv
                    sxy = P[0, 1] + jx * P[1, 2] + jy * P[0, 2] + jx * jy * P[2, 2] + mxy[i]
                    ia, ib, ic, det = _inv2(sxx, sxy, syy)
                    d2 = ia * ex * ex + 2 * ib * ex * ey + ic * ey * ey
                    if use_d and math.isfinite(dd[i]) and math.isfinite(dmean[qq]):
                        d2 += (dd[i] - dmean[qq]) ** 2 / dvar[qq]
                    if d2 <= new_chi2:
                        sep = False
                        break
                if not sep:
                    counters[C_AMBIG] += 1
                    continue
                if n_lm >= lm_xy.shape[0]:
                    counters[C_AMBIG] += 1  # no room (the caller grows the arrays)
                    continue
                j = n_lm
                n_lm += 1
                lm_xy[j, 0], lm_xy[j, 1] = wx[i], wy[i]
                lm_first[j] = f
                lm_inc[j] = -1
                lm_nobs[j] = 0
                lm_dsum[j] = 0.0
                lm_dn[j] = 0
                counters[C_NEW] += 1
            lm_nobs[j] += 1
            lm_last[j] = f
            if math.isfinite(dd[i]):
                lm_dsum[j] += dd[i]
                lm_dn[j] += 1
            # detection in the keyframe's sensor frame (dead reckoning within the window)
            pxs, pys = r[i] * math.cos(b[i]), r[i] * math.sin(b[i])
            out_j[n_out] = j
            out_kx[n_out] = qx + cq_ * pxs - sq_ * pys
            out_ky[n_out] = qy + sq_ * pxs + cq_ * pys
            out_wxy[n_out] = w_xy
            out_wth[n_out] = w_th
            n_out += 1
    trees, brg_w, rng_w, sig_w, n_skip = merge_window(
        out_j, out_kx, out_ky, out_wxy, out_wth, n_out, vr, vb, int(params[12])
    )
    return n_lm, n_out, trees, brg_w, rng_w, sig_w, n_skip


@numba.njit(cache=True, error_model="numpy")  # x / 0 -> inf, as the numpy code it replaced
def merge_window(
    out_j: np.ndarray,
    out_kx: np.ndarray,
    out_ky: np.ndarray,
    out_wxy: np.ndarray,
    out_wth: np.ndarray,
    n_out: int,
    vr: float,
    vb: float,
    min_obs: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """One bearing-range measurement per tree of a keyframe window (``track_keyframe`` output).

    The detections of a tree are averaged in the keyframe's sensor frame; the factor's variances
    are ``sigma^2 / n`` plus the window's odometry variance (``mxy`` on the position, ``mth``
    on the heading): ``sigma_r^2 = vr / n + mxy``, ``sigma_b^2 = vb / n + mxy / r^2 + mth``.
    Trees seen in fewer than ``min_obs`` scans of the window get no measurement.

    Returns ``(trees, bearing, range, sigmas (m, 2) as (sigma_b, sigma_r), n_skipped)``, trees
    in ascending id order. Sums run in detection order and the elementary functions are the
    C library's, as in the numpy ``unique`` + ``bincount`` formulation this replaces (~100 us
    of numpy calls per keyframe in the full run): the results are bit-identical.
    """
    trees = np.unique(out_j[:n_out])
    nt = trees.shape[0]
    slot = np.searchsorted(trees, out_j[:n_out])
    cnt = np.zeros(nt, dtype=np.int64)
    sx = np.zeros(nt)
    sy = np.zeros(nt)
    sxy = np.zeros(nt)
    sth = np.zeros(nt)
    for i in range(n_out):
        t = slot[i]
        cnt[t] += 1
        sx[t] += out_kx[i]
        sy[t] += out_ky[i]
        sxy[t] += out_wxy[i]
        sth[t] += out_wth[i]
    m = 0
    for t in range(nt):
        if cnt[t] >= min_obs:
            m += 1
    keep = np.empty(m, dtype=np.int64)
    brg = np.empty(m)
    rng = np.empty(m)
    sig = np.empty((m, 2))
    q = 0
    for t in range(nt):
        if cnt[t] < min_obs:
            continue
        c = float(cnt[t])
        mx, my, mxy, mth = sx[t] / c, sy[t] / c, sxy[t] / c, sth[t] / c
        r = math.hypot(mx, my)
        keep[q] = trees[t]
        brg[q] = math.atan2(my, mx)
        rng[q] = r
        sig[q, 0] = math.sqrt(vb / c + mxy / (r * r) + mth)
        sig[q, 1] = math.sqrt(vr / c + mxy)
        q += 1
    return keep, brg, rng, sig, nt - m


@numba.njit(cache=True)
def band_cho_solve(ub: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``A X = B`` from the banded Cholesky factor ``U`` (``A = Uᵀ U``), many right sides.

    ``ub`` (w + 1, n) is ``U`` in LAPACK's upper band storage (``ub[w + i - j, j] = U[i, j]``,
    as ``scipy.linalg.cholesky_banded`` returns it), ``b`` (n, m) C-ordered. LAPACK's
    ``dpbtrs`` solves one right-hand side at a time; here the inner loop runs along a row of
    ``B`` (contiguous), 5x faster for the ~800 right sides of the tree marginals.
    """
    w = ub.shape[0] - 1
    n, m = b.shape
    x = b.copy()
    for step in range(2):  # Uᵀ y = b (forward), then U x = y (backward)
        for t in range(n):
            r = t if step == 0 else n - 1 - t
            lo, hi = (max(0, r - w), r) if step == 0 else (r + 1, min(n, r + w + 1))
            for o in range(lo, hi):
                u = ub[w + o - r, r] if step == 0 else ub[w + r - o, o]  # Uᵀ[r, o] / U[r, o]
                for c in range(m):
                    x[r, c] -= u * x[o, c]
            d = ub[w, r]
            for c in range(m):
                x[r, c] /= d
    return x


def grow_landmarks(
    need: int, arrays: tuple[np.ndarray, ...], fills: tuple[float, ...]
) -> tuple[np.ndarray, ...]:
    """The tracker's per-landmark ``arrays`` grown (geometrically) to hold at least ``need``
    trees, the new rows set to ``fills`` (one value per array)."""
    n = arrays[0].shape[0]
    g = max(need, 2 * n) - n
    return tuple(
        np.concatenate((a, np.full((g, *a.shape[1:]), f, dtype=a.dtype)))
        for a, f in zip(arrays, fills, strict=True)
    )
