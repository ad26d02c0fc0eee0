"""Full-Stokes transfer blocks through ring FFTs and per-m GEMMs (north/south folded).

The coefficients of :mod:`mmflow.mmode.polarised` (correlation pq of baseline b against the sky's
T, E, B and V harmonics) on the same Gauss-Legendre grid, computed as the Stokes-I path computes
its own (:mod:`mmflow.mmode.transfer`). With ``F^X_{k,m} = sum_j f_b K_X(theta_k, phi_j) e^{i m phi_j}``
the ring FFT of the fringe times each Stokes kernel ``K_X`` of the correlation (X = I, V, Q, U) and
``W_lm, X_lm`` the spin-2 Legendre functions (:mod:`mmflow.mmode.spin_legendre`,
``+-2_lambda = W +- X``)::

    b^T_lm = sum_k w_k lambda_lm F^I_{k,m},          b^V_lm = sum_k w_k lambda_lm F^V_{k,m},
    b^E_lm = -sum_k w_k (W_lm F^Q_{k,m} + i X_lm F^U_{k,m}),
    b^B_lm =  sum_k w_k (W_lm F^U_{k,m} - i X_lm F^Q_{k,m}),

which is :func:`mmflow.mmode.polarised.polarised_coefficients`' ``-(int h_+ 2Y + int h_- -2Y)`` and
``-i (int h_+ 2Y - int h_- -2Y)`` with ``h_+- = f_b (K_Q +- i K_U) / 2`` written out. The stored
``-m`` row ``(-1)^m conj(b^X_{l,-m})`` is the same sum with ``conj(F^X_{k,-m})`` in place of
``F^X_{k,m}`` (``lambda_{l,-m} = (-1)^m lambda_lm``, ``W_{l,-m} = (-1)^m W_lm``,
``X_{l,-m} = -(-1)^m X_lm``). Folding ring k with its mirror k': ``lambda`` and ``W`` take
``F_k + F_k'`` on rows with ``l + m`` even and ``F_k - F_k'`` on odd rows; ``X`` the other way round.

Per m and correlation that is six real GEMMs of the Stokes-I path's shape (``lambda`` on I and V,
``W`` and ``X`` on Q and U) and four ring FFTs: a full-Stokes block costs ~24x a Stokes-I block's
Legendre step, and its Gram (4x the rows, 4x the columns) ~64x its ``herk``
(docs/stokes.md: measured by ``mmflow bench transfer --stokes IQUV``).
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import ducc0
import numpy as np

from mmflow.conventions import complex_dtype
from mmflow.mmode.fringe_kernels import kernel_fringe_folds, ring_fringes, scatter_m
from mmflow.mmode.polarised import CORRELATIONS, stokes_kernels
from mmflow.mmode.spin_legendre import weighted_spin_tables
from mmflow.threads import n_threads, single_threaded_blas

#: Order of the kernels on the Fourier arrays' field axis: the spin-0 pair, then the spin-2 pair.
FIELDS = ("I", "V", "Q", "U")
#: Bytes one pass's Fourier arrays may hold; more m than fit are done in blocks, each block's ring
#: FFTs recomputed (a quarter of the time at lmax 1000 with 8 baselines a pass: docs/stokes.md).
FOURIER_BUDGET_BYTES = 1024 * 2 ** 20
#: kernels (of one ring's 16, every baseline) folded and Fourier transformed at once in :func:`polarised_fourier`:
#: 2 x 2 x nb x n_phi complexes stay in cache from the fold to the copy (at lmax 1000, 64 baselines, 3430 points a
#: ring: 40 ms a ring with 2, 47 with 1, 46 with 4, 67 with all 16; docs/stokes.md)
KERNELS_PER_FFT = 2
#: baselines a pass (:func:`pass_baselines`): fewer narrow the GEMMs, more are not needed to fill them
PASS_BASELINES = (8, 64)


def active_rings(grid):
    """North-ring indices k whose ring or mirror ring sees a feed (the rest contribute nothing)."""
    seen = np.any(np.abs(grid.jn) + np.abs(grid.je) > 0, axis=(0, 2))
    half = len(grid.theta) // 2
    return np.flatnonzero(seen[:half] | seen[::-1][:half])


def ring_kernels(grid, k, correlations):
    """``K_X`` of ring k for X in :data:`FIELDS` and each correlation: complex ``(n_phi, 4, n_corr)``."""
    out = np.empty((grid.n_phi, 4, len(correlations)), complex)
    for c, corr in enumerate(correlations):
        k_i, k_q, k_u, k_v = stokes_kernels(grid.jn[:, k], grid.je[:, k], corr)
        out[:, 0, c], out[:, 1, c], out[:, 2, c], out[:, 3, c] = k_i, k_v, k_q, k_u
    return out


class FourierBuffers:
    """The two flat arrays :func:`polarised_fourier` writes ``F_k +/- F_k'`` into, kept for the blocks and
    passes of one caller's loop over baselines (:func:`polarised_pass`'s ``buffers``).

    Each block's arrays are up to a GB: above glibc's mmap threshold (32 MiB, :mod:`mmflow.allocator`) every
    fresh one is a new mapping whose pages fault in on first touch, 0.7-3.9 thread-s a pass of 15 baselines
    at lmax 1000 (docs/stokes.md). Grown, never shrunk, to the largest block asked (the old arrays freed
    before the larger ones are made). A block's arrays are written in full before they are read: the
    results are the same bits as with fresh arrays.
    """

    def __init__(self):
        self.flat = None

    def arrays(self, shape, dtype):
        """Two arrays ``shape`` of ``dtype``, views of the kept ones."""
        n = int(np.prod(shape))
        if self.flat is None or self.flat[0].dtype != np.dtype(dtype) or self.flat[0].size < n:
            self.flat = None
            self.flat = (np.empty(n, dtype), np.empty(n, dtype))
        return tuple(f[:n].reshape(shape) for f in self.flat)


def distinct_kernels(k_n, k_s):
    """The kernels a ring must transform: ``(distinct, copies, zero)`` with ``distinct`` the indices of the kernels
    ``(k_n[f], k_s[f])`` (north ring, mirror ring) that are neither zero on both rings (``zero``) nor equal, or
    opposite, to an earlier one, and ``copies[f] = [(f', +1 or -1), ...]`` the later kernels equal to ``+-``
    kernel f. The fold and the FFT are linear and negation is exact in floating point, so a copy's transforms are
    kernel f's (or their negation) bit for bit. Through a real Jones beam (the short dipole) V is zero in xx and
    yy and yx's I, Q, U, V are xy's, +, +, +, -: 10 of the 16 kernels are transformed
    (``tests/unit/mmode/test_polarised_fast.py``).
    """
    distinct, copies, zero = [], {}, []
    for f in range(len(k_n)):
        if not (k_n[f].any() or k_s[f].any()):
            zero.append(f)
            continue
        for d in distinct:
            sign = _same_up_to_sign(k_n[f], k_s[f], k_n[d], k_s[d])
            if sign:
                copies.setdefault(d, []).append((f, sign))
                break
        else:
            distinct.append(f)
    return distinct, copies, zero


def _same_up_to_sign(a_n, a_s, b_n, b_s):
    """+1 where kernel ``a`` equals kernel ``b`` on both rings, -1 where it equals ``-b``, else 0."""
    if np.array_equal(a_n, b_n) and np.array_equal(a_s, b_s):
        return 1
    if np.array_equal(a_n, -b_n) and np.array_equal(a_s, -b_s):
        return -1
    return 0


def polarised_fourier(grid, b, m_range, correlations=CORRELATIONS, cdtype=np.complex128, timings=None,
                      i_only=False, buffers=None):
    """``F_k +/- F_k'`` of every field and correlation for ``m0 <= m < m1`` and the active north rings.

    Returns
    -------
    fsum, fdiff : complex ``(m1 - m0, 2, n_active, 2, n_corr, 2 n_b)``: axes 1 and 3 are the
        field pairs (I, V) and (Q, U) of :data:`FIELDS` (each pair contiguous per m: one GEMM);
        columns ``c < n_b`` hold ``F_{k,m}`` of baseline c, ``c >= n_b`` hold ``F_{k,-m}`` of baseline
        ``c - n_b`` (conjugated after the GEMM, where the data are small). ``i_only`` (m above the
        polarised band limit, where only T is solved for): the I kernels alone, ``(m1 - m0, 1, n_active,
        1, n_corr, 2 n_b)``, a quarter of the ring products and FFTs. Views of ``buffers``'
        (:class:`FourierBuffers`) arrays where given, else new arrays.
    rings : the active north rings (:func:`active_rings`)
    """
    b = np.asarray(b, float).reshape(-1, 3)
    nb, nc, n = len(b), len(correlations), grid.n_phi
    m0, m1 = m_range
    rings = active_rings(grid)
    nf = 1 if i_only else 2
    shape = (m1 - m0, nf, len(rings), nf, nc, 2 * nb)
    fsum, fdiff = (buffers or FourierBuffers()).arrays(shape, cdtype)
    rdtype = np.dtype(cdtype).type(0).real.dtype

    def kernels(k):  # (kernel, phi): kernel = (field pair, field, correlation) of the Fourier arrays
        kern = ring_kernels(grid, k, correlations)
        return np.ascontiguousarray((kern[:, :1] if i_only else kern).reshape(n, -1).T)

    def ring(i):
        k = rings[i]
        ks = len(grid.theta) - 1 - k  # the mirror ring
        k_n, k_s = kernels(k), kernels(ks)
        distinct, copies, zero = distinct_kernels(k_n, k_s)
        for f in zero:  # a kernel zero on both rings (e.g. V of xx through a real Jones beam)
            a, x, c = np.unravel_index(f, (nf, nf, nc))
            for target in (fsum, fdiff):
                target[:, a, i, x, c] = 0
        if not distinct:
            return
        fringes = ring_fringes(grid.vectors[k], grid.vectors[ks], b, rdtype)
        folded = np.empty((2, KERNELS_PER_FFT, nb, n), cdtype)
        for g0 in range(0, len(distinct), KERNELS_PER_FFT):  # a few kernels at a time: fold, FFT, copy in cache
            group = distinct[g0:g0 + KERNELS_PER_FFT]
            g = len(group)
            kernel_fringe_folds(fringes, k_n[group], k_s[group], folded[0, :g], folded[1, :g])
            ducc0.fft.c2c(folded[:, :g], axes=(3,), forward=False, inorm=0, out=folded[:, :g], nthreads=1)
            for j, f in enumerate(group):  # each kernel, and the later ones equal to it up to sign
                out = [(f, 1)] + copies.get(f, [])
                index = np.unravel_index([o for o, _ in out], (nf, nf, nc))
                scatter_m(folded[:, j], fsum, fdiff, i, index, [s for _, s in out], m_range)

    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=n_threads()) as pool:
        list(pool.map(ring, range(len(rings))))
    if timings is not None:
        timings["fourier_s"] = timings.get("fourier_s", 0.0) + time.perf_counter() - t0
    return fsum, fdiff, rings


def fourier_bytes(n_active, nb, n_corr, itemsize):
    """Bytes of :func:`polarised_fourier`'s two arrays per m: ``2 x 2 x n_active x 2 x n_corr x 2 n_b``."""
    return 2 * 2 * int(n_active) * 2 * n_corr * 2 * nb * itemsize


def fourier_bytes_per_m(grid, nb, n_corr, itemsize):
    """:func:`fourier_bytes` on ``grid``'s active rings (:func:`active_rings`)."""
    return fourier_bytes(len(active_rings(grid)), nb, n_corr, itemsize)


def m_block_of(bytes_per_m, budget=None):
    """How many m one Fourier pass keeps so that its two arrays (``bytes_per_m`` each m) stay within ``budget``
    bytes (default :data:`FOURIER_BUDGET_BYTES`)."""
    budget = FOURIER_BUDGET_BYTES if budget is None else budget
    return max(1, int(budget // max(bytes_per_m, 1)))


def fourier_m_block(grid, nb, n_corr, itemsize, budget=None):
    """:func:`m_block_of` for ``nb`` baselines on ``grid``."""
    return m_block_of(fourier_bytes_per_m(grid, nb, n_corr, itemsize), budget)


def pass_baselines(bytes_per_m_baseline, n_pol_m, n_i_m, budget=None):
    """Baselines per :func:`polarised_pass` over ``n_pol_m`` m of every kernel and ``n_i_m`` m of the I
    kernels alone (above the polarised band limit: a quarter of the bytes), ``bytes_per_m_baseline`` the
    Fourier arrays' bytes per m and baseline (:func:`fourier_bytes_per_m`): as many as let each of the two
    ranges fit one Fourier m-block (:func:`fourier_m_block`), 8 to 64.

    Every m-block recomputes the rings' products and FFTs (the ring stage, not in the GEMMs), so a pass
    whose m do not fit one block pays it again per block: at lmax 1000 with Q, U, V to 256, 16 baselines a
    pass split the polarised m in two blocks, 36 ring products per baseline instead of 20. Below 8
    baselines the GEMMs narrow (measured at lmax 1000, every Stokes parameter to lmax, with numpy's ring
    products: 1.82 s per baseline at 8 a pass, 1.86 s at 4, 2.7 s at 16)."""
    budget = FOURIER_BUDGET_BYTES if budget is None else budget
    per = max(int(n_pol_m), -(-int(n_i_m) // 4), 1) * max(float(bytes_per_m_baseline), 1.0)
    return int(np.clip(budget // per, *PASS_BASELINES))


def baselines_per_pass(grid, n_corr, itemsize, budget=None, m_range=None, lmax_pol=None):
    """:func:`pass_baselines` for the passes of ``grid`` over ``m_range`` (default ``0..grid.lmax``), E, B and
    V to ``lmax_pol`` (default ``grid.lmax``)."""
    m0, m1 = (0, grid.lmax + 1) if m_range is None else (int(m_range[0]), min(int(m_range[1]), grid.lmax + 1))
    lpol = grid.lmax if lmax_pol is None else int(lmax_pol)
    n_pol_m = max(0, min(m1, lpol + 1) - m0)
    return pass_baselines(fourier_bytes_per_m(grid, 1, n_corr, itemsize), n_pol_m, m1 - m0 - n_pol_m, budget)


def legendre_rows(n_t, n_p):
    """Table x field rows of one m's Legendre GEMMs (:func:`polarised_block`): ``lambda`` on I to the T rows
    ``n_t`` and on V to the polarised rows ``n_p``, ``W`` and ``X`` on Q and U to ``n_p``."""
    return n_t + 5 * n_p


def polarised_tables(grid, m, lmax_rows, rings, rdtype, lmax_pol=None):
    """Weighted ``w lambda`` on the active north rings, rows ``l = m..lmax_rows``, and ``w W``, ``w X`` on rows
    ``l = m..lmax_pol`` (default ``lmax_rows``; :func:`polarised_block` takes E and B to there and no
    further), each as its ``(even, odd)`` rows in ``l - m`` (contiguous views, ``rdtype``;
    :func:`mmflow.mmode.spin_legendre.weighted_spin_tables`).

    Each row's entries below ``eps^2`` of its largest are zeroed as the kernel writes them (``flush``):
    a row's GEMM output is ``sum_k t_k F_k``, and such an entry moves it by less than ``eps`` of the
    rounding of its largest term. Near the poles ``lambda_lm`` of high m falls below float32's smallest
    normal number (2 % of the entries at lmax 1000), and those products ran through the CPU's subnormal
    path: one m's GEMM of the paper's shape took 7.4 ms with them and 0.74 ms without (1.0 ms for random
    data of the same shape; docs/stokes.md)."""
    tabs = weighted_spin_tables(m, lmax_rows, grid.theta[rings], grid.weights[rings], rdtype, flush=True,
                                lmax_spin=lmax_pol)
    return [(t[:(len(t) + 1) // 2], t[(len(t) + 1) // 2:]) for t in tabs]


def _folded_gemm(table, first, second, out):
    """``out[even rows] = even @ first``, ``out[odd rows] = odd @ second`` for ``table = (even, odd)``
    (rows ``l - m`` even and odd; complex data as real views: the tables are real)."""
    even, odd = table
    rdtype = even.dtype
    a, b = first.reshape(first.shape[0], -1), second.reshape(second.shape[0], -1)
    o = out.reshape(out.shape[0], -1)
    np.matmul(even, a.view(rdtype), out=o[0::2].view(rdtype))
    if len(odd):
        np.matmul(odd, b.view(rdtype), out=o[1::2].view(rdtype))


def _i_rows(lam, s_iv, d_iv, ne, no, n_rows):
    """I's rows from row ``ne + no`` of the ``lambda`` tables on (I, V) Fourier arrays ``s_iv, d_iv``
    (``(n_active, 2, n_corr, cols)``): ``(n_rows, n_corr, cols)``. The first of them is an odd row in
    ``l - m`` when ``ne > no`` (then the odd table and ``F_k - F_k'`` come first)."""
    s_i, d_i = np.ascontiguousarray(s_iv[:, 0]), np.ascontiguousarray(d_iv[:, 0])
    rest = np.empty((n_rows,) + s_i.shape[1:], s_iv.dtype)
    if ne > no:
        _folded_gemm((lam[1][no:], lam[0][ne:]), d_i, s_i, rest)
    else:
        _folded_gemm((lam[0][ne:], lam[1][no:]), s_i, d_i, rest)
    return rest


def polarised_block(s, d, tables, nb, n_pol=None):
    """One m's coefficients ``(n_out, 4, n_corr, 2 n_b)`` over STOKES (T, E, B, V), from that m's
    Fourier arrays ``s, d`` (:func:`polarised_fourier`: ``(2, n_active, 2, n_corr, 2 n_b)``, pairs
    (I, V) and (Q, U)) and the tables of :func:`polarised_tables`. ``n_pol`` (default ``n_out``): E, B
    and V are computed on the first ``n_pol`` rows only (their band limit, ``imaging.stokes_lmax``) and
    are zero above them; the spin-2 GEMMs shrink to those rows (none when ``n_pol = 0``), and the
    ``lambda`` GEMM takes the (I, V) pair on them and I alone on the rows above (:func:`_i_rows`)."""
    lam, wt, xt = tables
    n_out = lam[0].shape[0] + lam[1].shape[0]
    n_pol = n_out if n_pol is None else max(0, min(int(n_pol), n_out))
    if len(s) == 1 and n_pol:  # Fourier arrays of the I kernels alone (polarised_fourier's i_only)
        raise ValueError("polarised_block: E, B, V rows asked of the I kernels' Fourier arrays")
    out = np.zeros((n_out, 4) + s.shape[3:], s.dtype) if n_pol < n_out else np.empty((n_out, 4) + s.shape[3:],
                                                                                     s.dtype)
    ne, no = (n_pol + 1) // 2, n_pol // 2  # rows l - m even and odd below the band limit
    if len(s) == 1 or n_pol == n_out:  # I alone, or I and V on every row: one GEMM of the pair
        iv = np.empty((n_out,) + s.shape[2:], s.dtype)
        _folded_gemm(lam, s[0], d[0], iv)
    else:  # I and V on the rows below the band limit, I alone above it (V is zero there)
        iv = np.empty((n_pol,) + s.shape[2:], s.dtype)
        _folded_gemm((lam[0][:ne], lam[1][:no]), s[0], d[0], iv)
        rest = _i_rows(lam, s[0], d[0], ne, no, n_out - n_pol)
        np.conjugate(rest[..., nb:], out=rest[..., nb:])
        out[n_pol:, 0] = rest
    np.conjugate(iv[..., nb:], out=iv[..., nb:])
    out[:len(iv), 0] = iv[:, 0]
    if n_pol:
        out[:n_pol, 3] = iv[:n_pol, 1]
    if n_pol:
        wt_p, xt_p = (wt[0][:ne], wt[1][:no]), (xt[0][:ne], xt[1][:no])
        w_qu, x_qu = (np.empty((n_pol,) + s.shape[2:], s.dtype) for _ in range(2))
        _folded_gemm(wt_p, s[1], d[1], w_qu)
        _folded_gemm(xt_p, d[1], s[1], x_qu)
        for a in (w_qu, x_qu):
            np.conjugate(a[..., nb:], out=a[..., nb:])
        out[:n_pol, 1] = -(w_qu[:, 0] + 1j * x_qu[:, 1])
        out[:n_pol, 2] = w_qu[:, 1] - 1j * x_qu[:, 0]
    return out


def polarised_pass(grid, b, consume, mmax=None, correlations=CORRELATIONS, dtype=np.float64, lmax_rows=None,
                   timings=None, mmin=0, lmax_pol=None, buffers=None):
    """Compute every m's full-Stokes block of baselines ``b`` and hand it to ``consume(m, block)``.

    ``block`` is ``(n_out, 4, n_corr, cols)``, ``n_out = lmax_rows - m + 1`` (l = m..), axis 1
    :data:`mmflow.mmode.polarised.STOKES`, ``cols = n_b`` for m = 0 and ``2 n_b`` otherwise (the
    ``+m`` rows, then the ``-m`` rows ``(-1)^m conj(b^X_{l,-m})``). ``mmin <= m <= mmax`` (an m block
    of the stokes stage); ``lmax_pol``: E, B and V only to that l (zero above: :func:`polarised_block`).
    Runs of consecutive m run on :func:`mmflow.threads.n_threads` threads with one BLAS thread each (the
    bits do not depend on the thread count); ``consume`` is called on the thread that computed the block
    and may update per-m state without locks. Returns ``consume``'s results in m order. ``buffers``
    (:class:`FourierBuffers`): the Fourier arrays' memory, kept for the caller's next pass (default: kept for
    this pass's blocks only).
    """
    b = np.asarray(b, float).reshape(-1, 3)
    nb = len(b)
    lrows = grid.lmax if lmax_rows is None else min(int(lmax_rows), grid.lmax)
    mmax = lrows if mmax is None else min(int(mmax), lrows)
    lpol = lrows if lmax_pol is None else min(int(lmax_pol), lrows)
    rdtype = np.dtype(dtype)
    cdtype = complex_dtype(rdtype).type
    step = fourier_m_block(grid, nb, len(correlations), np.dtype(cdtype).itemsize)
    buffers = buffers or FourierBuffers()
    results = []
    # m <= lmax_pol: every kernel; above it the I kernels alone (a quarter of the arrays: 4x the m a block)
    ranges = [(m, min(m + step, mmax + 1, lpol + 1), False) for m in range(int(mmin), min(mmax, lpol) + 1, step)]
    ranges += [(m, min(m + 4 * step, mmax + 1), True) for m in range(max(int(mmin), lpol + 1), mmax + 1, 4 * step)]
    for m0, m1, i_only in ranges:
        fourier = polarised_fourier(grid, b, (m0, m1), correlations, cdtype, timings, i_only, buffers)
        per_task = max(1, 512 // (lrows + 1))
        tasks = [range(m, min(m + per_task, m1)) for m in range(m0, m1, per_task)]
        t0 = time.perf_counter()
        with single_threaded_blas(), ThreadPoolExecutor(max_workers=n_threads()) as pool:
            for res, tim in pool.map(lambda ms: _blocks(grid, fourier, m0, ms, lrows, lpol, nb, rdtype, consume),
                                     tasks):
                results.extend(res)
                if timings is not None:
                    for key, v in tim.items():
                        timings[key] = timings.get(key, 0.0) + v
        if timings is not None:
            timings["mpool_s"] = timings.get("mpool_s", 0.0) + time.perf_counter() - t0
        fourier = None  # one block's arrays at a time, in buffers' memory
    return results


def _blocks(grid, fourier, m0, ms, lrows, lpol, nb, rdtype, consume):
    """One pool task of :func:`polarised_pass`: the blocks of the m in ``ms`` handed to ``consume``."""
    fsum, fdiff, rings = fourier
    tim, res = {}, []
    for m in ms:
        t0 = time.perf_counter()
        tables = polarised_tables(grid, m, lrows, rings, rdtype, lpol)
        t1 = time.perf_counter()
        block = polarised_block(fsum[m - m0], fdiff[m - m0], tables, nb, lpol - m + 1)
        t2 = time.perf_counter()
        tim["tables_s"] = tim.get("tables_s", 0.0) + t1 - t0
        tim["legendre_s"] = tim.get("legendre_s", 0.0) + t2 - t1
        res.append(consume(m, block if m > 0 else block[..., :nb]))
    return res, tim


def polarised_transfer_blocks(grid, b_wavelengths, correlations=CORRELATIONS, dtype=np.float64):
    """Full-Stokes transfer blocks in the Stokes-I path's row layout, one per m (the fast path of
    :func:`mmflow.mmode.polarised.reference_transfer_blocks`: same layout, values to rounding).

    Returns
    -------
    list over ``m = 0..lmax`` of complex arrays ``(n_corr, 4, rows, lmax - m + 1)``.
    """
    return polarised_pass(grid, b_wavelengths, lambda m, blk: np.ascontiguousarray(blk.transpose(2, 1, 3, 0)),
                          correlations=correlations, dtype=dtype)
