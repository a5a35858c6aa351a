"""Fixed-interval smoothing of the EKF-SLAM path on the final map (ours; docs/algorithms/slam.md).

An EKF's pose at frame ``k`` uses the data up to ``k`` only; a loop closure later corrects the
map and the current pose (through the correlations in ``P``) but never the poses already
reported. On Victoria Park that is most of the EKF's remaining error: the path through new
ground before the closure at ~1,110 s keeps the drift it had then, while the map it delivers
has been corrected (docs/algorithms/slam.md, "EKF" item 8).

Here, after the filter, the whole path is re-estimated with the map held fixed: the maximum a
posteriori path given

* the pre-integrated odometry between consecutive frames (the increments and covariances the
  filter predicted with, :func:`stemmap.slam.motion.preintegrate_spans`), and
* every detection the filter associated with a landmark that is in the final map (merged
  landmarks follow their survivor), as a range-bearing measurement of the landmark's final
  position with the noise ``R + J_l P_jj J_lᵀ`` (the filter's detection noise plus the
  landmark's own final marginal; the map's cross-correlations are left out),

with the first pose fixed where the filter started it. The normal equations of this chain are
block-tridiagonal, so each Gauss-Newton step is one banded Cholesky solve, O(frames). For a
linear-Gaussian chain this least-squares solution is the Rauch-Tung-Striebel smoother (Rauch,
Tung & Striebel, AIAA J. 3(8), 1965); iterating it on the linearised models is the
Gauss-Newton form of the iterated smoother (Bell, "The iterated Kalman smoother as a
Gauss-Newton method", SIAM J. Optim. 4(3), 1994). The measurements carry a Huber weight on
their whitened norm (width 1.345, as :func:`stemmap.slam._graph_localise.localise_on_map`):
an association that fitted the map of its time may not fit the final one.

The covariance of each smoothed pose (issue 14, ``SlamResult.pose_covs``) is the diagonal
3x3 block of the inverse of the last Gauss-Newton information (the smoother's own normal
equations, Huber weights included), computed in O(frames) by the block form of the RTS
backward pass (:func:`chain_marginals`). It is the covariance of the path *given the final map*
with each detection's landmark uncertainty counted as independent noise, so it leaves out the
map's correlations; the map's joint error (the filter's landmark covariance, cross-terms
included) is then propagated through the smoother's normal equations and added
(:func:`map_propagated_covariance`, position and heading; without the joint covariance the
older approximation :func:`map_error_covariance`; docs/algorithms/slam.md, "Pose covariances of
the other back-ends").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np
from scipy.sparse import csr_matrix

from stemmap.slam._spill import SpilledColumn, SpilledRanges, SpilledRows
from stemmap.slam.base import IntArray
from stemmap.slam.treedb import range_bearing_jacobians
from stemmap.types import FloatArray, wrap_angle

__all__ = [
    "ObservationLog",
    "banded_lower",
    "chain_marginals",
    "eliminate_chain",
    "jacobian_rows",
    "map_error_covariance",
    "map_propagated_covariance",
    "odometry_terms",
    "rts_backward",
    "smooth_path",
]

# floor added to the odometry covariances: the Ackermann model has no lateral slip, so the
# increment covariance is singular (smallest eigenvalue ~1e-20 m² on Victoria Park; median
# 2.4e-6 m²); 1 mm / 1e-4 rad is below every noise the model does describe
_ODO_FLOOR = np.diag([1e-6, 1e-6, 1e-8])
_PRIOR_INFO = 1e10  # the first pose: the filter starts it with zero covariance
_CHUNK = 20_000  # measurements per block of the normal-equation assembly (memory bound)


_OBS_ROW = np.dtype(
    [("frame", np.int64), ("id", np.int64), ("range", np.float64), ("bearing", np.float64)]
)


class ObservationLog:
    """The associations a filter made: frame, landmark id, range, bearing per matched detection;
    merges are recorded so that a dropped landmark's detections follow the kept one.

    32 bytes per association in a :class:`~stemmap.slam._spill.SpilledRows` table: at most
    ``resident_rows`` of them in memory (default 65,536: 2 MB), older ones in a temporary file
    read back block by block by :meth:`stream` (the 10x Victoria Park soak logs ~490,000;
    docs/reliability.md "Soak").
    """

    def __init__(self, *, resident_rows: int = 1 << 16) -> None:
        self._rows = SpilledRows(_OBS_ROW, resident_rows=resident_rows, prefix="stemmap-obs-")
        self._alias: dict[int, int] = {}

    def add(self, frame: int, ids: IntArray, rng: FloatArray, brg: FloatArray) -> None:
        self._rows.append(frame=frame, id=ids, range=rng, bearing=brg)

    def merged(self, drop: int, keep: int) -> None:
        self._alias[int(drop)] = int(keep)

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def spilled(self) -> int:
        """Associations written to the temporary file."""
        return self._rows.spilled

    @property
    def resident_nbytes(self) -> int:
        return self._rows.resident_nbytes

    def close(self) -> None:
        """Remove the temporary file (after the smoother)."""
        self._rows.close()

    def stream(self, final_ids: IntArray) -> ResolvedObservations:
        """The logged detections whose landmark (after following merges) is in the final map,
        as ``(frame, index into final_ids, range, bearing)`` read block by block."""
        top: dict[int, int] = {}
        for d in self._alias:
            k = d
            while k in self._alias:
                k = self._alias[k]
            top[d] = k
        src = np.fromiter(top.keys(), dtype=np.int64, count=len(top))
        dst = np.fromiter(top.values(), dtype=np.int64, count=len(top))
        order = np.argsort(src)
        return ResolvedObservations(
            self._rows, src[order], dst[order], np.asarray(final_ids, dtype=np.int64)
        )

    def resolve(self, final_ids: IntArray) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
        """:meth:`stream`'s rows as four whole arrays (``(frame, index into final_ids, range,
        bearing)``)."""
        return self.stream(final_ids).arrays()


Observations = tuple[IntArray, IntArray, FloatArray, FloatArray]


class ResolvedObservations:
    """``(frame, landmark index, range, bearing)`` of an :class:`ObservationLog`'s detections
    on the final map, resolved chunk by chunk as the log is read (never all in memory)."""

    def __init__(
        self, rows: SpilledRows, src: IntArray, dst: IntArray, final_ids: IntArray
    ) -> None:
        self._rows, self._src, self._dst, self._fid = rows, src, dst, final_ids
        self._order = np.argsort(final_ids)
        self._size: int | None = None

    def _resolve(self, chunk: np.ndarray) -> Observations:
        ids = chunk["id"].copy()
        if self._src.size:
            at = np.minimum(np.searchsorted(self._src, ids), self._src.size - 1)
            hit = self._src[at] == ids
            ids[hit] = self._dst[at[hit]]
        fid, order = self._fid, self._order
        at = np.minimum(np.searchsorted(fid[order], ids), fid.size - 1)
        ok = fid[order][at] == ids
        return chunk["frame"][ok], order[at][ok], chunk["range"][ok], chunk["bearing"][ok]

    def blocks(self, size: int) -> Iterator[Observations]:
        """The resolved rows in log order, ``size`` at a time (the last block shorter)."""
        if not self._fid.size:  # every landmark was pruned
            return
        yield from _reblock((self._resolve(c) for c in self._rows.chunks()), size)

    @property
    def size(self) -> int:
        """Number of resolved rows (counted once by reading the log)."""
        if self._size is None:
            self._size = sum(int(b[0].size) for b in self.blocks(1 << 20))
        return self._size

    def arrays(self) -> Observations:
        """Every resolved row as four arrays (copies)."""
        parts = list(self.blocks(1 << 62))
        if not parts:
            e = np.zeros(0, dtype=np.int64)
            return e, e.copy(), np.zeros(0), np.zeros(0)
        return tuple(np.array(a) for a in parts[0])  # type: ignore[return-value]


class _ArrayObservations:
    """Four whole arrays with :class:`ResolvedObservations`' interface."""

    def __init__(self, obs: Observations) -> None:
        self._obs = obs
        self.size = int(obs[0].size)

    def blocks(self, size: int) -> Iterator[Observations]:
        for lo in range(0, self.size, size):
            sl = slice(lo, lo + size)
            yield self._obs[0][sl], self._obs[1][sl], self._obs[2][sl], self._obs[3][sl]

    def arrays(self) -> Observations:
        return self._obs


def _reblock(parts: Iterator[Observations], size: int) -> Iterator[Observations]:
    """Blocks of exactly ``size`` rows (the last one shorter, none empty) from parts of any
    length, in order."""
    held: list[Observations] = []
    n = 0
    for p in parts:
        while p[0].size:
            take = min(size - n, p[0].size)
            held.append(tuple(a[:take] for a in p))  # type: ignore[arg-type]
            p = tuple(a[take:] for a in p)  # type: ignore[assignment]
            n += take
            if n == size:
                yield _join(held)
                held, n = [], 0
    if n:
        yield _join(held)


def _join(parts: list[Observations]) -> Observations:
    if len(parts) == 1:
        return parts[0]
    return tuple(np.concatenate(cols) for cols in zip(*parts, strict=True))  # type: ignore[return-value]


def _measurement_terms(
    xs: FloatArray,
    L: FloatArray,
    Pl: FloatArray,
    rz: FloatArray,
    bz: FloatArray,
    a: float,
    b: float,
    R1: FloatArray,
    huber_k: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per measurement: ``w Jᵀ W J`` (m, 3, 3), ``w Jᵀ W e`` (m, 3), the whitened ``e``² and
    ``w J_vᵀ W J_l`` (m, 3, 2) (the gradient's sensitivity to the landmark) of the
    range-bearing of landmarks ``L`` (covariances ``Pl``) from vehicle poses ``xs``
    (observation model and Jacobians: :func:`stemmap.slam.treedb.range_bearing_jacobians`)."""
    z, Jv, Jl = range_bearing_jacobians(xs, L, (a, b))
    Wm = np.linalg.inv(R1[None] + Jl @ Pl @ Jl.transpose(0, 2, 1))
    em = np.column_stack((rz - z[:, 0], wrap_angle(bz - z[:, 1])))
    d2: FloatArray = np.einsum("mi,mij,mj->m", em, Wm, em)
    dn = np.sqrt(d2)
    w = np.where(dn <= huber_k, 1.0, huber_k / np.maximum(dn, 1e-12))
    JvT_W = w[:, None, None] * (Jv.transpose(0, 2, 1) @ Wm)
    return JvT_W @ Jv, np.einsum("mij,mj->mi", JvT_W, em), d2, JvT_W @ Jl


def odometry_terms(
    x: FloatArray, deltas: FloatArray, om: np.ndarray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Normal-equation blocks of the odometry factors between consecutive poses ``x`` (N, 3):
    ``h = [R(θa)ᵀ (p_b - p_a), θb - θa]`` against the increments ``deltas`` (N-1, 3) with
    information ``om`` (N-1, 3, 3). Returns ``Jaᵀ Ω Ja``, ``Jbᵀ Ω Jb``, ``Jbᵀ Ω Ja`` (N-1, 3, 3)
    and ``Jaᵀ Ω e``, ``Jbᵀ Ω e`` (N-1, 3), ``e = deltas - h`` (heading wrapped)."""
    pa, pb = x[:-1], x[1:]
    c, s = np.cos(pa[:, 2]), np.sin(pa[:, 2])
    dx, dy = pb[:, 0] - pa[:, 0], pb[:, 1] - pa[:, 1]
    h = np.column_stack((c * dx + s * dy, -s * dx + c * dy, pb[:, 2] - pa[:, 2]))
    e = deltas - h
    e[:, 2] = wrap_angle(e[:, 2])
    m = x.shape[0] - 1
    Ja = np.zeros((m, 3, 3))
    Ja[:, 0, 0], Ja[:, 0, 1], Ja[:, 0, 2] = -c, -s, -s * dx + c * dy
    Ja[:, 1, 0], Ja[:, 1, 1], Ja[:, 1, 2] = s, -c, -c * dx - s * dy
    Ja[:, 2, 2] = -1.0
    Jb = np.zeros((m, 3, 3))
    Jb[:, 0, 0], Jb[:, 0, 1] = c, s
    Jb[:, 1, 0], Jb[:, 1, 1] = -s, c
    Jb[:, 2, 2] = 1.0
    JaT_om = Ja.transpose(0, 2, 1) @ om
    JbT_om = Jb.transpose(0, 2, 1) @ om
    return (
        JaT_om @ Ja,
        JbT_om @ Jb,
        JbT_om @ Ja,
        np.einsum("nij,nj->ni", JaT_om, e),
        np.einsum("nij,nj->ni", JbT_om, e),
    )


def banded_lower(diag: FloatArray, off: FloatArray) -> FloatArray:
    """Lower banded storage (6, 3N) (:func:`scipy.linalg.solveh_banded`, ``lower=True``) of the
    block-tridiagonal symmetric matrix with diagonal blocks ``diag`` (N, 3, 3) and sub-diagonal
    blocks ``off`` (N-1, 3, 3) (``off[k]`` = block ``(k+1, k)``; N of them: the last one leads
    to the frame after the block, as a block of a longer chain stores it)."""
    n = diag.shape[0]
    ab = np.zeros((6, 3 * n))
    for i in range(3):
        for k in range(i + 1):
            ab[i - k, k::3] = diag[:, i, k]
        for k in range(3):
            ab[3 + i - k, k : 3 * off.shape[0] : 3] = off[:, i, k]
    return ab


def chain_marginals(diag: FloatArray, off: FloatArray) -> FloatArray:
    """Diagonal blocks (N, 3, 3) of ``H⁻¹`` for a block-tridiagonal SPD information ``H`` with
    diagonal blocks ``diag`` (N, 3, 3) and sub-diagonal blocks ``off`` (N-1, 3, 3) (``off[k]``
    = ``H[k+1, k]``).

    Forward elimination ``D_0 = H_00``, ``D_k = H_kk - B_k D_(k-1)⁻¹ B_kᵀ`` (the information of
    pose k given the measurements up to k), then the backward pass of the Rauch-Tung-Striebel
    smoother in information form (Rauch, Tung & Striebel 1965): ``Σ_(N-1) = D_(N-1)⁻¹``,
    ``Σ_k = D_k⁻¹ + G_k Σ_(k+1) G_kᵀ`` with ``G_k = D_k⁻¹ B_(k+1)ᵀ`` (the conditional of pose k
    given pose k+1 has mean ``-G_k x_(k+1)`` and covariance ``D_k⁻¹``).
    """
    out = rts_backward(eliminate_chain(diag, off), off)
    return 0.5 * (out + out.transpose(0, 2, 1))


def eliminate_chain(
    diag: FloatArray, off: FloatArray, d_prev: FloatArray | None = None,
    b_prev: FloatArray | None = None,
) -> FloatArray:  # fmt: skip
    """:func:`chain_marginals`' forward elimination ``D_k⁻¹`` (N, 3, 3) of a block of the
    chain; ``d_prev``, ``b_prev``: the previous block's last ``D⁻¹`` and the block linking
    it to this one's first frame (None at the start of the chain)."""
    n = diag.shape[0]
    d_inv = np.empty((n, 3, 3))
    d = diag[0] if d_prev is None or b_prev is None else diag[0] - b_prev @ d_prev @ b_prev.T
    for k in range(n):
        if k:
            b = off[k - 1]
            d = diag[k] - b @ d_inv[k - 1] @ b.T
        d_inv[k] = np.linalg.inv(0.5 * (d + d.T))
    return d_inv


def rts_backward(d_inv: FloatArray, off: FloatArray, after: FloatArray | None = None) -> FloatArray:
    """:func:`chain_marginals`' backward pass over a block (not yet symmetrised); ``after``:
    the next block's first marginal (None at the end of the chain; ``off`` then has one block
    per frame, the last leading to the next block's first frame)."""
    n = d_inv.shape[0]
    out = np.empty((n, 3, 3))
    if after is None:
        out[-1] = d_inv[-1]
    else:
        g = d_inv[-1] @ off[n - 1].T
        out[-1] = d_inv[-1] + g @ after @ g.T
    for k in range(n - 2, -1, -1):
        g = d_inv[k] @ off[k].T
        out[k] = d_inv[k] + g @ out[k + 1] @ g.T
    return out


def smooth_path(
    poses: FloatArray | SpilledColumn,
    deltas: FloatArray | SpilledColumn,
    covs: FloatArray | SpilledColumn,
    obs: Observations | ResolvedObservations,
    lm_xy: FloatArray,
    lm_cov: FloatArray,
    sensor_offset: tuple[float, float],
    R1: FloatArray,
    *,
    huber_k: float = 1.345,
    iterations: int = 20,
    map_cov: FloatArray | None = None,
    map_cov_inflation: float = 1.0,
) -> tuple[FloatArray, FloatArray, dict[str, float | int]]:
    """The vehicle path (N, 3) re-estimated on the fixed final map and the covariance of each
    pose (N, 3, 3) from the last step's normal equations (module docstring).

    poses : (N, 3) the filter's vehicle poses (start of the iteration; ``poses[0]`` is fixed)
    deltas, covs : (N-1, 3) / (N-1, 3, 3) odometry increments between consecutive frames in the
        earlier frame's vehicle frame and their covariances (these three: arrays, or columns
        of a table on disk, :class:`stemmap.slam._ekf_stream.FrameInputs`; read by slices)
    obs : ``(frame, landmark, range, bearing)`` per associated detection: four arrays, or an
        :class:`ObservationLog`'s :meth:`~ObservationLog.stream` (read block by block at every
        step, so the measurements are never all in memory; the same result)
    lm_xy, lm_cov : (L, 2) / (L, 2, 2) final landmark positions and marginal covariances
    sensor_offset : (a, b) of the sensor in the vehicle frame; R1 : (2, 2) detection noise
    map_cov : (2L, 2L), optional, the filter's joint covariance of the final landmarks (order of
        ``lm_xy``); with it the map's error is propagated through the smoother
        (:func:`map_propagated_covariance`), without it approximated from the marginals
        (:func:`map_error_covariance`)
    map_cov_inflation : factor (>= 0) on that map term of the covariance (not on the path); 1
        is the model's own (``EkfConfig.map_cov_inflation``)

    Returns the path, its covariances and stats (iterations, measurements used, mean whitened
    residual² of the measurements before and after, the share down-weighted by Huber at the
    end).

    Memory: every Gauss-Newton step is a forward sweep over the frames in order and a
    backward sweep in reverse blocks (:mod:`stemmap.slam._ekf_stream`): the normal equations,
    their factor, the iterates and the chain marginals' elimination go to temporary files
    ``_SEG`` frames at a time and the measurements are read ``_CHUNK`` at a time, so beside
    the inputs and the returned path and covariances the working set does not grow with the
    drive; the result is the whole-band solve's bit for bit (docs/reliability.md "Soak").
    """
    from stemmap.slam import _ekf_stream as st

    n = len(poses)
    a, b = sensor_offset
    ob = _ArrayObservations(obs) if isinstance(obs, tuple) else obs
    n_obs = ob.size
    stats: dict[str, float | int] = {"smoother_measurements": n_obs}
    if n < 2:  # the first pose is fixed where the filter started it
        first = np.full((n, 3, 3), 1.0 / _PRIOR_INFO) * np.eye(3)
        return np.array(poses[0:n], dtype=np.float64), first, stats

    def terms(
        fr: IntArray, lj: IntArray, rz: FloatArray, bz: FloatArray, xs: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        return _measurement_terms(xs, lm_xy[lj], lm_cov[lj], rz, bz, a, b, R1, huber_k)

    def reader(store: SpilledRanges | None) -> Callable[[int, int], FloatArray]:
        if store is None:
            return lambda lo, hi: np.array(poses[lo:hi], dtype=np.float64)
        return lambda lo, hi: store.get(lo, hi)[0]

    prior = np.array(poses[0:1], dtype=np.float64)[0]
    cur: SpilledRanges | None = None  # the iterate (None: the filter's poses)
    lin: SpilledRanges | None = None  # the iterate the last step was linearised at
    step: st.StreamedStep | None = None
    it, d2_sum, n_huber = 0, 0.0, 0
    for it in range(1, iterations + 1):
        if step is not None:
            step.close()
        if lin is not None:
            lin.close()
        lin, at = cur, reader(cur)
        step = st.StreamedStep(n, at, prior, deltas, covs, st._SEG)
        d2_sum, n_huber = step.assemble(ob, terms, huber_k)
        if it == 1:
            stats["smoother_meas_d2_before"] = d2_sum / n_obs if n_obs else math.nan
        cur = SpilledRanges("stemmap-path-")
        big_xy = big_th = 0.0
        for lo, hi, dx in step.solution():
            xs = at(lo, hi) + dx
            xs[:, 2] = wrap_angle(xs[:, 2])
            cur.put(lo, (xs,))
            big_xy = max(big_xy, float(np.abs(dx[:, :2]).max()))
            big_th = max(big_th, float(np.abs(dx[:, 2]).max()))
        if big_xy < 1e-4 and big_th < 1e-6:
            break
    assert step is not None and cur is not None
    stats["smoother_iterations"] = it
    stats["smoother_meas_d2_after"] = d2_sum / n_obs if n_obs else math.nan
    stats["smoother_huber_share"] = n_huber / n_obs if n_obs else 0.0
    cov = st.chain_marginals_streamed(step)
    k_map = float(map_cov_inflation)
    if map_cov is not None:
        # the gradient's sensitivity to the map at the last step's linearisation point
        at = reader(lin)

        def sensitivities() -> Iterator[tuple[IntArray, IntArray, FloatArray]]:
            for fr, lj, rz, bz in ob.blocks(_CHUNK):
                f0 = int(fr[0])
                *_, Bm = terms(fr, lj, rz, bz, at(f0, int(fr[-1]) + 1)[fr - f0])
                yield fr, lj, Bm

        term = st.map_term_streamed(step, sensitivities(), map_cov)
        cov[1:] += k_map * term[1:]
    else:
        fr, lj, _, _ = ob.arrays()
        cov[1:, :2, :2] += (
            k_map * map_error_covariance(n, fr, lm_cov[lj] if lj.size else lm_cov[:0])[1:]
        )
    x = np.empty((n, 3))
    for lo, hi in step.spans:
        x[lo:hi] = cur.get(lo, hi)[0]
    for done in (step, cur, lin):
        if done is not None:
            done.close()
    return x, cov, stats


def jacobian_rows(frame: IntArray, lm: IntArray, Bm: FloatArray, n: int, m2: int) -> csr_matrix:
    """Rows ``3 frame .. 3 frame + 2`` (``frame`` in ``[0, n)``, non-decreasing) of ``B``
    (the sensitivity ``∂g/∂L`` of :func:`map_propagated_covariance`) from the 3x2 blocks
    ``Bm`` at landmarks ``lm``, canonical CSR (a row's entries are its frame's, so any cut
    between frames gives the same rows)."""
    r = 3 * frame[:, None, None] + np.arange(3)[None, :, None]
    c = 2 * lm[:, None, None] + np.arange(2)[None, None, :]
    rc = (np.broadcast_to(r, Bm.shape).ravel(), np.broadcast_to(c, Bm.shape).ravel())
    return csr_matrix((Bm.reshape(-1), rc), shape=(3 * n, m2))


def map_propagated_covariance(
    diag: FloatArray,
    off: FloatArray,
    frame: IntArray,
    lm: IntArray,
    Bm: FloatArray,
    map_cov: FloatArray,
    *,
    columns: int = 128,
    block_mb: float = 32.0,
    seg: int = 1024,
) -> FloatArray:
    """(N, 3, 3) covariance the map's joint error adds to the smoothed path (ours, issue 14).

    The smoother's step solves ``H δx = g(L)`` on the fixed map ``L``; to first order an error
    ``δL`` of the map moves the solution by ``δx = -H⁻¹ B δL``, ``B = ∂g/∂L`` stacked from the
    per-measurement blocks ``Bm = w J_vᵀ W J_l`` (3x2, at landmark ``lm``, frame ``frame``),
    so with the filter's joint landmark covariance ``Σ_LL`` (``map_cov``, cross-correlations
    included) the path's covariance gains ``H⁻¹ B Σ_LL Bᵀ H⁻¹`` (the standard propagation of a
    "consider" parameter's covariance through a least-squares estimate, e.g. Bierman,
    "Factorization Methods for Discrete Sequential Estimation", 1977, ch. VIII). Its diagonal
    3x3 blocks are computed column block by column block: ``Σ_LL = U Uᵀ`` (Cholesky), ``M =
    H⁻¹ (B U)`` by one banded Cholesky of ``H`` (the block-tridiagonal information of
    :func:`smooth_path`), ``Σ_k += M_k M_kᵀ`` (an eigen-factor where ``Σ_LL`` is not
    numerically positive definite). A common shift *and rotation* of the landmarks a
    pose sees reach its position and heading with the lever arms of the geometry. The map's
    error is taken as independent of the detections' noise (the landmarks were estimated from
    the same detections, which would make the sum slightly smaller: conservative).

    A column block holds ``3 N x columns`` doubles, two copies alive at a time (``B U`` and
    the solve's Fortran-ordered copy, then the solution and its C-ordered reshape): at most
    ``columns`` columns, fewer where that would pass ``block_mb`` MB (on the 10x Victoria Park
    soak, N = 72,490 frames, 128 columns were ~220 MB a copy and made this the EKF's peak,
    1.24 GB; docs/reliability.md "Soak"). The result does not depend on the block size (up to
    the order of a floating-point sum). Computed by
    :func:`stemmap.slam._ekf_stream.map_term_streamed` (what :func:`smooth_path` runs) on a
    step holding ``diag``/``off`` factored ``seg`` frames at a time
    (:meth:`~stemmap.slam._ekf_stream.StreamedStep.of_chain`).
    """
    from stemmap.slam import _ekf_stream as st

    step = st.StreamedStep.of_chain(diag, off, seg)
    order = np.argsort(frame, kind="stable")  # (the rows' entries keep their order)
    sens = iter([(frame[order], lm[order], Bm[order])]) if frame.size else iter([])
    try:
        return st.map_term_streamed(step, sens, map_cov, columns=columns, block_mb=block_mb)
    finally:
        step.close()


def map_factor(map_cov: FloatArray) -> FloatArray:
    """``U`` with ``U Uᵀ`` = the symmetrised ``map_cov`` (Cholesky; an eigen-factor where the
    filter's ``P`` is marginally indefinite)."""
    S = 0.5 * (map_cov + map_cov.T)
    try:
        U: FloatArray = np.linalg.cholesky(S)  # type: ignore[assignment]
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(S)
        U = V * np.sqrt(np.clip(w, 0.0, None))
    return U


def map_columns(n: int, columns: int, block_mb: float) -> int:
    """Columns of ``U`` per block of the map term: at most ``columns``, fewer where one block
    (3 ``n`` x columns doubles) would pass ``block_mb`` MB."""
    return max(1, min(int(columns), int(block_mb * 2**20 / (3 * n * 8))))


def map_error_covariance(n: int, frame: IntArray, seen_cov: FloatArray) -> FloatArray:
    """(n, 2, 2) position covariance the map's own error adds to a pose localised on it (ours,
    issue 14): the mean marginal covariance of the landmarks each frame detected (``frame`` and
    ``seen_cov``, one per detection); frames without detections interpolate between the
    nearest frames with (constant beyond the ends; zero without any detection).

    The smoother's information counts each detection's landmark uncertainty as independent
    noise, so many detections average it away; but the landmarks one pose sees were mapped
    from the same drifting poses and share their error. Taking them as fully correlated in
    translation, a common map shift ``δ`` shifts the pose by ``δ`` (``J Σ_LL Jᵀ`` with the
    sensitivity of a rigid fit to a translation of all its points = the identity): the pose's
    error relative to the world is its error relative to the map plus the map's local error.
    The heading's share (a map rotation) is left out; the start pose, which defines the map
    frame, gets none (the caller skips row 0). Measured in docs/outputs.md.
    """
    out = np.zeros((n, 2, 2))
    if frame.size == 0:
        return out
    cnt = np.bincount(frame, minlength=n).astype(np.float64)
    have = np.flatnonzero(cnt > 0)
    fi = np.arange(n)
    for i, j in ((0, 0), (0, 1), (1, 1)):
        m = np.bincount(frame, weights=seen_cov[:, i, j], minlength=n)[have] / cnt[have]
        out[:, i, j] = np.interp(fi, have, m)
    out[:, 1, 0] = out[:, 0, 1]
    return out
