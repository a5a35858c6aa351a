"""The EKF path smoother's normal equations solved frame block by frame block (ours).

:func:`stemmap.slam._ekf_smooth.smooth_path` solves, at every Gauss-Newton step, ``H δ = g``
with ``H`` block-tridiagonal (3x3 blocks per frame: the odometry chain plus the measurements;
lower half-bandwidth ``KD = 5`` in LAPACK's banded storage), then takes the chain marginals of
the last ``H`` (the Rauch-Tung-Striebel backward pass in information form; Rauch, Tung &
Striebel, AIAA J. 3(8), 1965) and propagates the map's joint covariance through it. Held
whole, that is ~0.85 kB per frame (the band, its factor, ``diag``/``off``, the iterates, the
marginals) plus 72 bytes per measurement: 95 MB at 10x Victoria Park. Here every pass is a
forward sweep over the frames in order (assembly, Cholesky factor, forward substitution, the
elimination of the chain marginals), ``_SEG`` frames at a time, whose per-frame results go to
a temporary file (:class:`stemmap.slam._spill.SpilledRanges`), and a backward sweep reading
them back last block first (back substitution, the RTS pass, the map term). The working set
is a few blocks whatever the drive length, beside the products (path, covariances, the map
term's (N, 3, 3) sum) and the map term's forward solution of one column block (3 N x columns
doubles, at most ``block_mb`` = 32 MB: the same bound, and the same column blocks, as the whole
solve's); the estimates are those of the whole-band solve **bit for bit**, on any CPU:

* **Factor and substitutions** are :mod:`stemmap.slam._band_kernel`'s (numba, no
  ``fastmath``): the right-looking band Cholesky, column ``j`` divided by ``√a_jj`` and its
  outer product subtracted from the next ``KD`` columns, and the column-oriented forward
  substitution, run over the block's ``m`` columns with the band and right-hand side
  extending ``KD`` past them: those ``KD`` columns / rows then hold every update from the
  block's columns and nothing else, and are carried into the next block, whose loop goes on
  with them exactly where the whole-band loop would. The back substitution of a block reads
  the next block's first ``KD`` rows of the solution. One implementation for the whole band
  and for the blocks, so a block and its carry are the same loop run in pieces. (Before,
  LAPACK's ``dpbtrf`` / ``dtbtrs`` factored and solved each block and numpy re-did
  ``dpbtf2``'s arithmetic at the seams; that matched one call over the whole band only where
  the BLAS kernel OpenBLAS picks for the CPU rounds as the emulation did: on an AVX-512 Xeon
  it did not, and the path changed in its 14th digit with the drive's length.)
* **Assembly.** Each diagonal block gets at most two odometry terms on a zero (their order
  does not change a bit) and then the measurement terms in the log's order (``np.add.at`` on
  the same rows); the measurements are read in the same ``_CHUNK`` blocks as before (the
  residual sums are taken per block).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np
from scipy.sparse import csr_matrix

import stemmap.slam._band_kernel as bk
import stemmap.slam._ekf_smooth as sm
from stemmap.slam._band_kernel import KD
from stemmap.slam._spill import SpilledColumn, SpilledRanges, SpilledRows, SpillFile
from stemmap.slam.base import IntArray
from stemmap.types import FloatArray, wrap_angle

__all__ = [
    "KD",
    "FrameInputs",
    "StreamedStep",
    "band_backward",
    "band_forward",
    "chain_marginals_streamed",
    "map_term_streamed",
]

_SEG = 1024  # frames per block of the sweeps


def band_forward(
    lt: FloatArray, rhs: FloatArray, m: int, *, factor: bool
) -> tuple[FloatArray, FloatArray]:
    """Factor (``factor``) and forward-substitute the leading ``m`` columns of a banded block
    (:mod:`stemmap.slam._band_kernel`).

    lt : (c, KD+1) band of columns ``[s, s + c)`` (``lt[j, i] = H[s + j + i, s + j]``, the
        factor's if not ``factor``), ``c >= m + KD`` unless the block is the last of the
        matrix (``c = m``); its first ``KD`` rows (and those of ``rhs``) hold what the
        previous block carried
    rhs : (rows, r) right-hand sides, ``rows >= m + KD`` unless the block is the last
        (``rows = m``)

    Returns copies: the band (the factor if ``factor``) with rows ``[0, m)`` final and ``[m,
    m + KD)`` carried, and the forward solution ``L⁻¹ rhs`` likewise.
    """
    t = np.array(lt, dtype=np.float64, order="C")
    if factor and (info := bk.band_factor(t, m)):
        raise np.linalg.LinAlgError(f"smoother information not positive definite ({info})")
    y = np.array(rhs, dtype=np.float64, order="C")
    if bk.band_forward(t, y, m):
        raise np.linalg.LinAlgError("singular smoother factor")
    return t, y


def band_backward(t: FloatArray, y: FloatArray, after: FloatArray | None) -> FloatArray:
    """Back substitution ``L⁻ᵀ y`` of one block (factor ``t`` (m, KD+1), forward solution
    ``y`` (m, r)) given the solution's first ``KD`` rows of the next block (``after``; None
    for the last block)."""
    m = t.shape[0]
    z = np.array(y[:m] if after is None else np.concatenate((y[:m], after[:KD])), order="C")
    if bk.band_back(np.ascontiguousarray(t), z, m):
        raise np.linalg.LinAlgError("singular smoother factor")
    return z[:m]


class StreamedStep:
    """One Gauss-Newton step of :func:`~stemmap.slam._ekf_smooth.smooth_path`, streamed.

    ``x_at(lo, hi)`` gives the current iterate's poses ``[lo, hi)``; ``deltas``/``covs`` slice
    like arrays. :meth:`assemble` reads the measurements once, builds the normal equations as
    frames complete and factors / forward-solves them ``seg`` frames at a time into a
    temporary file (per frame: the factor's 3 columns, the forward solution, ``diag``,
    ``off``); :meth:`solution` yields the step last block first.
    """

    def __init__(
        self, n: int, x_at: Callable[[int, int], FloatArray], prior: FloatArray,
        deltas: FloatArray | SpilledColumn, covs: FloatArray | SpilledColumn, seg: int,
    ) -> None:  # fmt: skip
        self.n, self.x_at, self.prior = n, x_at, np.asarray(prior, dtype=np.float64)
        self.deltas, self.covs, self.seg = deltas, covs, max(2, int(seg))
        self.factor = SpilledRanges("stemmap-factor-")  # per frame: 3 factor columns, L⁻¹g
        self.chain = SpilledRanges("stemmap-chain-")  # per frame: diag, off
        self.spans: list[tuple[int, int]] = []
        self._w0 = self._e = 0  # window: frames [w0, e) entered
        self._diag = np.zeros((0, 3, 3))
        self._off = np.zeros((0, 3, 3))
        self._g = np.zeros((0, 3))
        self._ahead: tuple[FloatArray, FloatArray] | None = None  # next frame's Hbb, gb
        self._carry: tuple[FloatArray, FloatArray] | None = None

    @classmethod
    def of_chain(cls, diag: FloatArray, off: FloatArray, seg: int = 1024) -> StreamedStep:
        """A step that holds given block-tridiagonal normal equations (``diag``, ``off`` as
        :func:`~stemmap.slam._ekf_smooth.banded_lower` takes them; zero gradient), factored
        ``seg`` frames at a time: what :func:`map_term_streamed` and
        :func:`chain_marginals_streamed` need, for an information matrix built elsewhere."""
        n = diag.shape[0]
        step = cls(n, lambda lo, hi: np.zeros((hi - lo, 3)), np.zeros(3), np.zeros((0, 3)),
                   np.zeros((0, 3, 3)), seg)  # fmt: skip
        step._diag, step._off = np.array(diag, dtype=np.float64), np.array(off, dtype=np.float64)
        step._g, step._e = np.zeros((n, 3)), n
        for complete in range(step.seg + 2, n, step.seg):
            step._push(complete)
        step._push(n, final=True)
        return step

    def _enter(self, upto: int) -> None:
        """Frames ``[e, upto)`` (at most ``seg`` more) with their prior / odometry terms."""
        e, hi = self._e, upto
        if hi <= e:
            return
        cnt = hi - e
        Z, Zo, G = np.zeros((cnt, 3, 3)), np.zeros((cnt, 3, 3)), np.zeros((cnt, 3))
        if e == 0:
            Z[0] += sm._PRIOR_INFO * np.eye(3)
            e0 = self.prior - self.x_at(0, 1)[0]
            e0[2] = wrap_angle(e0[2])
            G[0] += sm._PRIOR_INFO * e0
        elif self._ahead is not None:
            Z[0] += self._ahead[0]
            G[0] += self._ahead[1]
        k1 = min(hi, self.n - 1)  # odometry factors [e, k1); factor k: frames k, k + 1
        if k1 > e:
            om = np.linalg.inv(self.covs[e:k1] + sm._ODO_FLOOR)
            Haa, Hbb, Hba, ga, gb = sm.odometry_terms(self.x_at(e, k1 + 1), self.deltas[e:k1], om)
            nk, inside = k1 - e, min(k1 - e, cnt - 1)
            Z[:nk] += Haa
            Zo[:nk] += Hba
            G[:nk] += ga
            Z[1 : 1 + inside] += Hbb[:inside]
            G[1 : 1 + inside] += gb[:inside]
            self._ahead = (Hbb[-1], gb[-1]) if nk > inside else None
        self._diag = np.concatenate((self._diag, Z))
        self._off = np.concatenate((self._off, Zo))
        self._g = np.concatenate((self._g, G))
        self._e = hi

    def _advance(self, to: int) -> None:
        """Enter the frames before ``to`` (none of them gets more terms), ``seg`` at a time,
        factoring as blocks complete."""
        while self._e < to:
            self._enter(min(to, self._e + self.seg))
            self._push(self._e)
        self._push(to)

    def _push(self, complete: int, *, final: bool = False) -> None:
        """Factor the window's frames before ``complete``: all of them if ``final``, else all
        but the two the carry reaches into, once there are ``seg`` of those."""
        k = complete - self._w0
        nf = k if final else k - 2
        if nf < (1 if final else self.seg):
            return
        lt = np.ascontiguousarray(sm.banded_lower(self._diag[:k], self._off[:k]).T)
        rhs = self._g[:k].reshape(-1, 1).copy()
        if self._carry is not None:
            lt[:KD], rhs[:KD] = self._carry
        m = 3 * nf
        t, y = band_forward(lt, rhs, m, factor=True)
        w0 = self._w0
        self.factor.put(w0, (t[:m].reshape(nf, 3, KD + 1), y[:m].reshape(nf, 3)))
        self.chain.put(w0, (self._diag[:nf], self._off[:nf]))
        self.spans.append((w0, w0 + nf))
        self._carry = None if final else (t[m : m + KD].copy(), y[m : m + KD].copy())
        self._diag, self._off, self._g = self._diag[nf:], self._off[nf:], self._g[nf:]
        self._w0 = w0 + nf

    def assemble(
        self, ob: sm.ResolvedObservations | sm._ArrayObservations, terms: MeasTerms, huber_k: float
    ) -> tuple[float, int]:
        """Build, factor and forward-solve the step's normal equations; ``terms(fr, lj, rz, bz,
        xs)`` are a measurement block's ``_measurement_terms`` at poses ``xs``. Returns the
        sum of the whitened residuals² and the number of Huber-weighted measurements."""
        d2_sum, n_huber = 0.0, 0
        for fr, lj, rz, bz in ob.blocks(sm._CHUNK):
            f0 = int(fr[0])
            H_m, g_m, d2, _ = terms(fr, lj, rz, bz, self.x_at(f0, int(fr[-1]) + 1)[fr - f0])
            d2_sum += float(d2.sum())
            n_huber += int((d2 > huber_k * huber_k).sum())
            i = 0
            while i < fr.size:  # (np.add.at row by row: the same sums in any cut)
                j = int(np.searchsorted(fr, fr[i] + self.seg))
                self._advance(int(fr[i]))
                self._enter(int(fr[j - 1]) + 1)
                w = fr[i:j] - self._w0
                np.add.at(self._diag, w, H_m[i:j])
                np.add.at(self._g, w, g_m[i:j])
                i = j
        self._advance(self.n)
        self._push(self.n, final=True)
        return d2_sum, n_huber

    def solution(self) -> Iterator[tuple[int, int, FloatArray]]:
        """``(lo, hi, step (hi - lo, 3))`` per block, last block first."""
        after = None
        for lo, hi in reversed(self.spans):
            band, y = self.factor.get(lo, hi)
            after = band_backward(_band(band), y.reshape(-1, 1), after)
            yield lo, hi, after.reshape(-1, 3)

    def close(self) -> None:
        self.factor.close()
        self.chain.close()


MeasTerms = Callable[
    [IntArray, IntArray, FloatArray, FloatArray, FloatArray],
    tuple[FloatArray, FloatArray, FloatArray, FloatArray],
]


def _band(rows: FloatArray) -> FloatArray:
    """(nf, 3, KD+1) per-frame factor rows -> (3 nf, KD+1) band (``lt``)."""
    return rows.reshape(-1, KD + 1)


def chain_marginals_streamed(step: StreamedStep) -> FloatArray:
    """:func:`~stemmap.slam._ekf_smooth.chain_marginals` of the step's ``diag``/``off``
    (read block by block; the (N, 3, 3) result is the product)."""
    d_inv = SpilledRanges("stemmap-chain-")
    d_prev = b_prev = None
    for lo, hi in step.spans:
        diag, off = step.chain.get(lo, hi)
        di = sm.eliminate_chain(diag, off, d_prev, b_prev)
        d_inv.put(lo, (di,))
        d_prev, b_prev = di[-1], off[-1]
    out = np.empty((step.n, 3, 3))
    nxt = None
    for lo, hi in reversed(step.spans):
        _, off = step.chain.get(lo, hi)
        (di,) = d_inv.get(lo, hi)
        blk = sm.rts_backward(di, off, nxt)
        nxt = blk[0]
        out[lo:hi] = 0.5 * (blk + blk.transpose(0, 2, 1))
    d_inv.close()
    return out


def map_term_streamed(
    step: StreamedStep, sens: Iterator[tuple[IntArray, IntArray, FloatArray]], map_cov: FloatArray,
    *, columns: int = 128, block_mb: float = 32.0,
) -> FloatArray:  # fmt: skip
    """:func:`~stemmap.slam._ekf_smooth.map_propagated_covariance` streamed: ``B`` (the
    per-measurement sensitivities ``sens``, frames non-decreasing) kept per block in a
    temporary file, ``H⁻¹ B U`` solved block by block on the step's factor for each column
    block of ``U`` (the same column blocks as the whole solve: the same sums)."""
    n, m2 = step.n, map_cov.shape[0]
    out = np.zeros((n, 3, 3))
    store = SpillFile("stemmap-mapterm-")
    chunks, nnz = _b_parts(step.spans, sens, m2, store)
    if nnz == 0 or m2 == 0:
        store.close()
        return out
    U = sm.map_factor(map_cov)
    columns = sm.map_columns(n, columns, block_mb)
    spans = step.spans

    def bu(i: int, Uc: np.ndarray) -> FloatArray:
        lo, hi = spans[i]
        data, indices, indptr = store.read(chunks[i])
        return csr_matrix((data, indices, indptr), shape=(3 * (hi - lo), m2)) @ Uc

    for c0 in range(0, m2, columns):
        Uc = U[:, c0 : c0 + columns]
        ys: list[FloatArray] = []  # L⁻¹ B U_c: 3 N x columns doubles at most (block_mb)
        carry, nxt = None, bu(0, Uc)
        for i, (lo, hi) in enumerate(spans):
            rhs, last = nxt, i == len(spans) - 1
            if carry is not None:
                rhs[:KD] = carry
            if not last:
                nxt = bu(i + 1, Uc)
                rhs = np.concatenate((rhs, nxt[:KD]), axis=0)
            band, _ = step.factor.get(lo, hi)
            m = 3 * (hi - lo)
            _, y = band_forward(_band(band), rhs, m, factor=False)
            ys.append(y[:m])
            carry = y[m : m + KD]
        after = None
        for lo, hi in reversed(spans):
            band, _ = step.factor.get(lo, hi)
            after = band_backward(_band(band), ys.pop(), after)
            M = after.reshape(hi - lo, 3, -1)
            out[lo:hi] += M @ M.transpose(0, 2, 1)
    store.close()
    return out


def _b_parts(
    spans: list[tuple[int, int]], sens: Iterator[tuple[IntArray, IntArray, FloatArray]], m2: int,
    store: SpillFile,
) -> tuple[list[int], int]:  # fmt: skip
    """``B``'s rows of each block ``[lo, hi)`` of ``spans`` as a CSR (data, indices, indptr)
    chunk of ``store`` (:func:`~stemmap.slam._ekf_smooth.jacobian_rows`: the rows of the whole
    ``B``). Returns the chunk indices and the number of entries."""
    chunks: list[int] = []
    nnz = 0
    held: list[tuple[IntArray, IntArray, FloatArray]] = []

    def emit(lo: int, hi: int) -> None:
        nonlocal held, nnz
        fr, lm, Bm = (np.concatenate(p) for p in zip(*held, strict=True)) if held else _NONE
        k = int(np.searchsorted(fr, hi))
        part = sm.jacobian_rows(fr[:k] - lo, lm[:k], Bm[:k], hi - lo, m2)
        chunks.append(store.append((part.data, part.indices, part.indptr)))
        nnz += part.nnz
        held = [(fr[k:], lm[k:], Bm[k:])] if k < fr.size else []

    for blk in sens:
        held.append(blk)
        while len(chunks) < len(spans) and blk[0][-1] >= spans[len(chunks)][1]:
            emit(*spans[len(chunks)])
    while len(chunks) < len(spans):
        emit(*spans[len(chunks)])
    return chunks, nnz


_NONE = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 3, 2)))


_ODO_ROW = np.dtype([("delta", np.float64, (3,)), ("cov", np.float64, (3, 3))])
_POSE_ROW = np.dtype([("pose", np.float64, (3,))])


class FrameInputs:
    """The smoother's per-frame inputs in bounded memory: the pre-integrated odometry between
    consecutive frames (96 bytes per frame, :func:`stemmap.slam.motion.preintegrate_spans`)
    and the filter's poses (24 bytes per frame, appended as the filter goes), each at most
    ``resident_rows`` rows in memory and the rest in a temporary file
    (:class:`~stemmap.slam._spill.SpilledRows`; the same bytes read back).

    :meth:`odometry` yields the increments in frame order (the filter's prediction);
    :attr:`poses`, :attr:`deltas`, :attr:`covs` slice like arrays (the smoother's reads).
    """

    def __init__(self, deltas: FloatArray, covs: FloatArray, *, resident_rows: int = 4096) -> None:
        self._odo = SpilledRows(_ODO_ROW, resident_rows=resident_rows, prefix="stemmap-odo-")
        for lo in range(0, deltas.shape[0], resident_rows):
            hi = lo + resident_rows
            self._odo.append(delta=deltas[lo:hi], cov=covs[lo:hi])
        self._path = SpilledRows(_POSE_ROW, resident_rows=resident_rows, prefix="stemmap-poses-")
        self.deltas: SpilledColumn = self._odo.column("delta")
        self.covs: SpilledColumn = self._odo.column("cov")
        self.poses: SpilledColumn = self._path.column("pose")

    def odometry(self) -> Iterator[tuple[FloatArray, FloatArray]]:
        """``(delta, cov)`` from frame f to f + 1, for f = 0, 1, ..."""
        for chunk in self._odo.chunks():
            d, c = chunk["delta"], chunk["cov"]
            for i in range(d.shape[0]):
                yield d[i], c[i]

    def add_pose(self, pose: FloatArray) -> None:
        self._path.append(pose=np.asarray(pose)[None])

    def path(self) -> FloatArray:
        """(N, 3) every pose added."""
        return self._path.rows(0, len(self._path))["pose"]

    def close(self) -> None:
        self._odo.close()
        self._path.close()
