"""Transfer matrices ``B_m`` through ring FFTs and one real GEMM per m (north/south folded).

For baseline b (sky frame at ``phi = 0``, in wavelengths) the baseline transfer function is
``f_b(r) = A(r) exp(2 pi i b . r)``, and

``B_lm(b) = int f_b Y_lm dOmega = sum_k w_k lambda_lm(theta_k) F_{k,m}(b)``,
``F_{k,m}(b) = sum_j f_b(theta_k, phi_j) exp(+i m phi_j)``

on a Gauss-Legendre grid (``w_k`` includes ``2 pi / n_phi``). The quadrature is exact when
``f_b`` is band-limited to ``L_f`` and the grid is exact to ``lmax + L_f``. The -m row of
b is the +m row of -b: ``F_{k,m}(-b) = conj(F_{k,-m}(b))``, so one FFT gives both rows.
Folding rings ``k`` and ``pi - theta_k`` with ``lambda_lm(pi-theta) = (-1)^{l+m} lambda_lm(theta)``
halves the GEMM: even ``l+m`` use ``F_k + F_k'``, odd use ``F_k - F_k'``.

Kernels here are numpy/ducc0 (and one numba loop, :mod:`mmflow.mmode.fringe_kernels`) on
in-memory arrays; dask maps them over chunks. Within a call, rings (Fourier stage, one ring per
task so that its FFT buffers stay in cache) and runs of consecutive m (:func:`transfer_pass`:
Legendre GEMMs, then the caller's per-m step, e.g. the Gram update, on the same thread) run on
:func:`mmflow.threads.n_threads` threads with one BLAS thread each: the bits of every block do
not depend on the thread count.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import ducc0
import numpy as np

from mmflow.conventions import SPEED_OF_LIGHT, enu_to_equatorial_matrix, m_blocks, unit_vectors, complex_dtype
from mmflow.mmode.fringe_kernels import fringe_folds
from mmflow.mmode.legendre import weighted_legendre_table
from mmflow.threads import n_threads, single_threaded_blas


def fringe_bandlimit(b_wavelengths, beam_lmax):
    """Band limit of ``A exp(2 pi i b.r)``: ``2 pi |b| + 3 (2 pi |b|)^(1/3) + beam + 8``.

    Beyond ``l ~ 2 pi |b|`` the fringe's harmonic content falls like a Bessel function
    past its turning point; the cube-root term covers the transition region.
    """
    kb = 2 * np.pi * float(np.max(b_wavelengths, initial=0.0))
    return int(np.ceil(kb + 3 * kb ** (1 / 3) + beam_lmax + 8))


@dataclass
class QuadratureGrid:
    """A Gauss-Legendre grid in the sky frame at ``phi = 0`` (what scalar and polarised transfers share).

    Attributes
    ----------
    lmax : int
        Largest l of the transfer coefficients computed on this grid.
    quad_lmax : int
        Band limit the quadrature is exact to (``lmax + L_f``).
    theta, weights : ndarray (n_theta,)
    n_phi : int
    vectors : ndarray (n_theta, n_phi, 3) directions
    """

    lmax: int
    quad_lmax: int
    theta: np.ndarray
    weights: np.ndarray
    n_phi: int
    vectors: np.ndarray


@dataclass
class TransferGrid(QuadratureGrid):
    """A :class:`QuadratureGrid` with the beam sampled on it.

    Attributes
    ----------
    beam : ndarray (n_theta, n_phi) float64, zero below the horizon
    active : ndarray of int
        North-ring indices k whose ring or mirror ring sees the beam.
    """

    beam: np.ndarray
    active: np.ndarray
    _tables: dict = field(default_factory=dict, repr=False)
    _work: dict = field(default_factory=dict, repr=False)

    def workspace(self, shape, dtype):
        """Two reusable buffers (first-touch page faults of fresh GB arrays are not free)."""
        key = (shape, np.dtype(dtype).str)
        if key not in self._work:
            self._work.clear()
            self._work[key] = (np.zeros(shape, dtype), np.zeros(shape, dtype))
        return self._work[key]

    @property
    def n_theta(self):
        return len(self.theta)

    def tables(self, m, dtype, l_block=256):
        """Weighted Legendre tables ``w_k lambda_lm(theta_k)`` in l-blocks, split by parity of ``l - m``.

        Returns a list of ``(i0, k0, even, odd)`` for l-blocks starting at ``l = m + i0``: rings
        before ``k0`` (poleward of the block's turning point, where ``lambda_lm ~ sin^m theta``
        is below the working precision -- 1e-15 (float64) or 1e-9 (float32) of the table's
        peak -- for every l in the block) are dropped from that block's GEMM.
        """
        key = (m, np.dtype(dtype).str)
        if key not in self._tables:
            north = self.active
            t, colmax = weighted_legendre_table(m, self.lmax, self.theta[north], self.weights[north], dtype, l_block)
            tol = (1e-9 if np.dtype(dtype) == np.float32 else 1e-15) * max(colmax.max(initial=0.0), 1e-300)
            blocks = []
            for j, i0 in enumerate(range(0, t.shape[0], l_block)):
                above = colmax[j] > tol
                k0 = int(np.argmax(above)) if above.any() else t.shape[1]
                sub = t[i0:i0 + l_block, k0:]
                blocks.append((i0, k0, np.ascontiguousarray(sub[0::2]), np.ascontiguousarray(sub[1::2])))
            self._tables[key] = blocks
        return self._tables[key]


def grid_rings(lmax, fringe_lmax):
    """Rings of the Gauss-Legendre grid exact to ``lmax + fringe_lmax`` (even: rings pair up north/south)."""
    n_theta = (lmax + fringe_lmax) // 2 + 2
    return n_theta + n_theta % 2


def make_grid(lat_rad, beam, freq_hz, lmax, fringe_lmax):
    """Build the quadrature grid exact to ``lmax + fringe_lmax`` and sample the beam on it."""
    quad = lmax + fringe_lmax
    n_theta = grid_rings(lmax, fringe_lmax)
    n_phi = ducc0.fft.good_size(quad + 2)
    theta = ducc0.misc.GL_thetas(n_theta)
    weights = ducc0.misc.GL_weights(n_theta, n_phi)
    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    vec = unit_vectors(theta[:, None], phi[None, :])
    enu = vec @ enu_to_equatorial_matrix(lat_rad)  # r_enu = M^T r_eq
    a = beam.power_enu(enu, freq_hz)
    half = n_theta // 2
    seen = (a[:half].max(axis=1) > 0) | (a[::-1][:half].max(axis=1) > 0)
    return TransferGrid(lmax, quad, theta, weights, n_phi, vec, a, np.flatnonzero(seen))


def _ring_fourier(grid, b, start, stop, mmax, cdtype, fsum, fdiff):
    """Fill ``fsum/fdiff[m, k, :]`` for north-ring slots ``start..stop``.

    By linearity the FFT of (north +/- south) gives ``F_k +/- F_k'`` directly, the two
    inputs of the parity-split Legendre GEMMs. Columns ``nb..2nb-1`` receive ``F_{-m}``
    (conjugated after the GEMM, where the data are small).
    """
    nb = len(b)
    ks = grid.active[start:stop]
    vec = grid.vectors[ks]
    zrot = np.exp(-4j * np.pi * vec[:, :1, 2] * b[None, :, 2])  # (nr, nb): mirror ring b.r' = b.r - 2 b_z z
    north = np.empty((len(ks), grid.n_phi, nb), cdtype)
    south = np.empty_like(north)
    fringe_folds(vec, b, grid.beam[ks], grid.beam[grid.n_theta - 1 - ks], zrot, north, south)
    n = grid.n_phi
    for f, target in ((north, fsum), (south, fdiff)):
        # one FFT thread: the ring blocks themselves run in parallel (iter_transfer_blocks' pool)
        ducc0.fft.c2c(f, axes=(1,), forward=False, inorm=0, out=f, nthreads=1)
        target[:, start:stop, :nb] = f[:, :mmax + 1, :].transpose(1, 0, 2)
        # F_{-m} for m = 0..mmax: index 0, then n-1, n-2, ... (a reversed slice, no gather)
        neg = target[:, start:stop, nb:]
        neg[0] = f[:, 0, :]
        if mmax > 0:
            neg[1:] = f[:, n - 1:n - 1 - mmax:-1, :].transpose(1, 0, 2)


def fourier_stage(grid, b_wavelengths, mmax, dtype=np.float64, ring_block=1, timings=None):
    """``F_k +/- F_k'`` for every m and north ring: the two inputs of the Legendre GEMMs.

    Returns ``(fsum, fdiff)``, each ``(mmax + 1, n_active, 2 n_b)`` in the grid's reused
    workspace (valid until the next call on this grid). Rings run in a pool of
    :func:`mmflow.threads.n_threads` threads, one FFT thread each: the bits do not depend on
    the thread count.
    """
    b = np.asarray(b_wavelengths, float).reshape(-1, 3)
    cdtype = complex_dtype(dtype).type
    nn = len(grid.active)
    # fsum[m, k, c] = F_{k,m} + F_{k',m} for north ring k and its mirror k'; fdiff the difference.
    # Columns c < nb are the baselines, c >= nb the reversed baselines (the -m rows).
    fsum, fdiff = grid.workspace((mmax + 1, nn, 2 * len(b)), cdtype)
    bounds = [(s0, min(s0 + ring_block, nn)) for s0 in range(0, nn, ring_block)]
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=n_threads()) as pool:
        list(pool.map(lambda se: _ring_fourier(grid, b, se[0], se[1], mmax, cdtype, fsum, fdiff), bounds))
    _add(timings, "fourier_s", time.perf_counter() - t0)
    return fsum, fdiff


def _add(timings, key, value):
    if timings is not None:
        timings[key] = timings.get(key, 0.0) + value


def transfer_pass(grid, b_wavelengths, consume, lmax_b=None, mmax=None, dtype=np.float64, lmax_rows=None,
                  column_scale=None, timings=None):
    """Compute ``B_m`` for ``m = 0..mmax`` and hand each to ``consume(m, out, timings)`` on a pool thread.

    ``out`` is C-ordered ``(L, 2 n_b)``, ``L = lmax_rows - m + 1``: ``out[l - m, c]`` for baseline
    ``c < n_b`` (``+m``) and ``c >= n_b`` (the ``-m`` row of baseline ``c - n_b``), with
    coefficients ``l > lmax_b`` zeroed and column ``c`` multiplied by ``column_scale[c mod n_b]``.
    Each m is computed and consumed by one task (one BLAS thread), so ``consume`` may update
    per-m state without locks and the bits do not depend on the thread count.
    Returns the list of ``consume``'s results in m order.

    Parameters
    ----------
    lmax_rows : int, optional
        Largest l computed (default the grid's lmax): a chunk may use a larger grid than it needs.
    timings : dict, optional
        Accumulates ``fourier_s`` (wall), ``mpool_s`` (wall of the per-m stage) and, summed over
        threads, ``tables_s``, ``legendre_s``, ``legendre_flops``, ``scale_s`` and ``consume``'s own keys.
    """
    b = np.asarray(b_wavelengths, float).reshape(-1, 3)
    nb = len(b)
    lrows = grid.lmax if lmax_rows is None else min(int(lmax_rows), grid.lmax)
    mmax = lrows if mmax is None else min(mmax, lrows)
    rdtype = np.dtype(dtype)
    fsum, fdiff = fourier_stage(grid, b, mmax, rdtype, timings=timings)
    lmax_b = np.full(nb, lrows) if lmax_b is None else np.minimum(np.asarray(lmax_b), lrows)
    scale = None
    if column_scale is not None or np.any(lmax_b < lrows):
        # one multiplier per (l, column): the mask l <= lmax_b times the column weight
        col = np.ones(nb) if column_scale is None else np.asarray(column_scale, float)
        lb2, col2 = np.concatenate([lmax_b, lmax_b]), np.concatenate([col, col])
        scale = ((np.arange(lrows + 1)[:, None] <= lb2[None, :]) * col2[None, :]).astype(rdtype)
    threads = n_threads()
    # consecutive m per task: small blocks in larger tasks keep the hand-over small next to the work
    per_task = max(1, 2048 // (lrows + 1))
    tasks = [range(m0, m1) for m0, m1 in m_blocks(mmax, per_task)]

    def run(ms):
        tim = {}
        res = []
        for m in ms:
            out = _legendre_block(grid, fsum, fdiff, m, nb, rdtype, lrows, tim)
            if scale is not None:
                t0 = time.perf_counter()
                np.multiply(out, scale[m:], out=out)
                tim["scale_s"] = tim.get("scale_s", 0.0) + time.perf_counter() - t0
            res.append(consume(m, out, tim))
        return res, tim

    t0 = time.perf_counter()
    results = []
    # each task's GEMMs on one BLAS thread (always: the same bits for any thread budget)
    with single_threaded_blas(), ThreadPoolExecutor(max_workers=threads) as pool:
        for res, tim in pool.map(run, tasks):
            results.extend(res)
            if timings is not None:
                for k, v in tim.items():
                    timings[k] = timings.get(k, 0.0) + v
    _add(timings, "mpool_s", time.perf_counter() - t0)
    return results


def iter_transfer_blocks(grid, b_wavelengths, lmax_b=None, mmax=None, dtype=np.float64, ring_block=1,
                         timings=None, lmax_rows=None):
    """Yield ``(m, B_m)`` for ``m = 0..mmax`` for a chunk of baselines.

    Parameters
    ----------
    grid : TransferGrid
    b_wavelengths : ndarray (n_b, 3)
        Baselines in the sky frame at ``phi = 0``, in wavelengths.
    lmax_b : ndarray (n_b,), optional
        Per-baseline lmax; coefficients with ``l > lmax_b`` are set to zero.
    dtype : float32 or float64
        Precision of the GEMM and of the blocks (complex64 / complex128 out).
    ring_block : int
        Unused (kept for callers); rings are one per Fourier task.
    timings : dict, optional
        Accumulates ``fourier_s``, ``legendre_s`` and ``legendre_flops`` (for benchmarks).
    lmax_rows : int, optional
        Largest l of the blocks (default the grid's lmax).

    Yields
    ------
    m : int
    B_m : ndarray, shape ``(n_b, L)`` for m = 0 and ``(2 n_b, L)`` for m > 0, ``L = lmax_rows - m + 1``;
        columns are ``l = m..lmax_rows``; rows ``n_b..2n_b-1`` are the -m rows (see conventions).
    """
    nb = len(np.asarray(b_wavelengths).reshape(-1, 3))
    blocks = transfer_pass(grid, b_wavelengths, lambda m, out, tim: out, lmax_b, mmax, dtype, lmax_rows,
                           timings=timings)
    for m, out in enumerate(blocks):
        yield m, (out.T if m > 0 else out[:, :nb].T)


def _legendre_block(grid, fsum, fdiff, m, nb, rdtype, lrows, timings):
    """``B_m`` as ``(L, 2 nb)``, ``L = lrows - m + 1``: parity-split GEMMs of the weighted tables with ``F +/- F'``."""
    cdtype = fsum.dtype
    nn = fsum.shape[1]
    t0 = time.perf_counter()
    tables = grid.tables(m, rdtype)
    t1 = time.perf_counter()
    n_out = lrows - m + 1
    out = np.zeros((n_out, 2 * nb), cdtype)
    flops = 0.0
    for i0, k0, even, odd in tables:
        if k0 >= nn or i0 >= n_out:
            continue
        s = fsum[m, k0:].view(rdtype)  # (nn - k0, 4 nb) real view
        d = fdiff[m, k0:].view(rdtype)
        # l - m even rows use F + F', odd rows F - F' (i0 is even: blocks keep parity)
        ne = min(len(even), (n_out - i0 + 1) // 2)
        no = min(len(odd), (n_out - i0) // 2)
        np.matmul(even[:ne], s, out=out[i0:i0 + 2 * ne:2].view(rdtype))
        if no > 0:
            np.matmul(odd[:no], d, out=out[i0 + 1:i0 + 1 + 2 * no:2].view(rdtype))
        flops += 2.0 * (ne + no) * even.shape[1] * s.shape[1]
    np.conjugate(out[:, nb:], out=out[:, nb:])  # B_{-m}(b) = conj(T F_{-m}(b)): T is real
    t2 = time.perf_counter()
    timings["tables_s"] = timings.get("tables_s", 0.0) + t1 - t0
    timings["legendre_s"] = timings.get("legendre_s", 0.0) + t2 - t1
    timings["legendre_flops"] = timings.get("legendre_flops", 0.0) + flops
    return out


def transfer_blocks(grid, b_wavelengths, lmax_b=None, mmax=None, dtype=np.float64):
    """All blocks of :func:`iter_transfer_blocks` in a list indexed by m."""
    return [blk for _, blk in iter_transfer_blocks(grid, b_wavelengths, lmax_b, mmax, dtype)]


def baselines_in_wavelengths(telescope, pairs, freq_hz):
    """Baseline vectors of ``pairs`` in the sky frame at ``phi = 0``, in wavelengths."""
    b_enu = telescope.baselines_enu(pairs)
    return b_enu @ enu_to_equatorial_matrix(telescope.lat_rad).T * freq_hz / SPEED_OF_LIGHT
