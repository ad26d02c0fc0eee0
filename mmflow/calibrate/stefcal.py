"""Stefcal: per-antenna complex gains by alternating least squares (diagonal Jones, per pol).

Model ``V_ij = g_i conj(g_j) M_ij``. Holding every gain but ``g_j`` fixed, the least-squares
update of antenna ``j`` over all baselines ``i`` and all samples ``k`` (integrations, channels)
of one solution is (Salvini & Wijnholds 2014; Mitchell et al. 2008)::

    Z_ji   = M_ji conj(g_i)
    N_j    = sum_k sum_i w_ji V_ji conj(Z_ji)
    D_j    = sum_k sum_i w_ji |Z_ji|^2
    g_j   <- N_j / D_j

(written for row ``j`` of the Hermitian antenna matrix; the same as
``N_j = sum_i (G_i M_ij)^H V_ij`` for the column). All antennas are updated at once from the
previous gains. Damping: ``"half"`` averages new and old gains on even iterations;
``"rk4"`` integrates the update field ``f(g) = step(g) - g`` with one classical Runge-Kutta
step per iteration; ``"none"`` takes the raw step. Convergence when
``||g_new - g|| / ||g|| < tol`` per solution.

Autocorrelations carry zero weight (the diagonal is never used). The overall phase is
fixed afterwards by a reference antenna (the one with most unflagged weight, i.e. fewest
flags, unless given). The numba kernels accumulate in complex128 whatever the input dtype and
run independent solutions concurrently (``nogil``) on :func:`mmflow.threads.n_threads`
threads.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np

from mmflow.calibrate.baselines import check_pairs, to_matrix
from mmflow.calibrate.outliers import antenna_statistics, outliers
from mmflow.errors import InputError
from mmflow.threads import n_threads
from mmflow.conventions import complex_dtype

DAMPING = ("half", "rk4", "none")


@numba.njit(nogil=True, cache=True)
def _residual_power(V, M, W, g, chi, cnt, j0, j1):
    """``chi[s, j] = sum_k sum_i w_ji |V_ji - g_j M_ji conj(g_i)|^2``; ``cnt``: terms with w > 0."""
    S, K, N = V.shape[0], V.shape[1], V.shape[2]
    for s in range(S):
        for j in range(j0, j1):
            c = 0.0
            n = 0.0
            gj = g[s, j]
            for k in range(K):
                for i in range(N):
                    w = W[s, k, j, i]
                    if w == 0.0 or i == j:
                        continue
                    r = V[s, k, j, i] - gj * M[s, k, j, i] * np.conj(g[s, i])
                    c += w * (r.real * r.real + r.imag * r.imag)
                    n += 1.0
            chi[s, j] = c
            cnt[s, j] = n


@lru_cache(maxsize=4)
def _pool(threads):
    return ThreadPoolExecutor(threads, thread_name_prefix="mmflow-stefcal")


def run_rows(kernel, n_rows, args, threads=None):
    """Run ``kernel(*args, j0, j1)`` over antenna-row blocks on a persistent thread pool.

    The numba kernels release the GIL; rows (not solutions) are split so that a single
    integration also uses every thread.
    """
    threads = max(1, min(n_threads() if threads is None else threads, n_rows))
    if threads == 1:
        kernel(*args, 0, n_rows)
        return
    b = np.linspace(0, n_rows, threads + 1).astype(int)
    list(_pool(threads).map(lambda k: kernel(*args, b[k], b[k + 1]), range(threads)))


@numba.njit(nogil=True, cache=True, fastmath=True)
def _sweep_upper(V, M, W, g, active, num, den, j0, j1):
    """Accumulate ``N`` and ``D`` of every antenna from the upper triangle rows ``j0..j1``.

    Uses the Hermitian symmetry (``V_ij = conj(V_ji)``, same for M, ``w_ij = w_ji``): element
    (j, i > j) adds ``w V_ji conj(M_ji) g_i`` to ``N_j`` and ``w conj(V_ji) M_ji g_j`` to ``N_i``
    (and ``w |M_ji|^2 |g|^2`` to D), reading half the matrix. ``num`` and ``den`` (S, N) belong
    to this row block (summed by the caller).
    """
    S, K, N = V.shape[0], V.shape[1], V.shape[2]
    for s in range(S):
        if not active[s]:
            continue
        for j in range(j0, j1):
            gjr = g[s, j].real
            gji = g[s, j].imag
            gj2 = gjr * gjr + gji * gji
            nr = 0.0
            ni = 0.0
            d = 0.0
            for k in range(K):
                for i in range(j + 1, N):
                    w = W[s, k, j, i]
                    mr = M[s, k, j, i].real
                    mi = M[s, k, j, i].imag
                    vr = V[s, k, j, i].real
                    vi = V[s, k, j, i].imag
                    gir = g[s, i].real
                    gii = g[s, i].imag
                    # a = V_ji conj(M_ji)
                    ar = vr * mr + vi * mi
                    ai = vi * mr - vr * mi
                    m2 = w * (mr * mr + mi * mi)
                    nr += w * (ar * gir - ai * gii)
                    ni += w * (ar * gii + ai * gir)
                    d += m2 * (gir * gir + gii * gii)
                    # conj(a) g_j into N_i
                    num[s, i] += w * complex(ar * gjr + ai * gji, ar * gji - ai * gjr)
                    den[s, i] += m2 * gj2
            num[s, j] += complex(nr, ni)
            den[s, j] += d


def _upper_bounds(n_rows, parts):
    """Row blocks of the upper triangle with about equal numbers of elements."""
    work = np.cumsum(np.arange(n_rows, 0, -1) - 1.0)
    cuts = np.searchsorted(work, work[-1] * np.arange(1, parts) / parts)
    return np.concatenate([[0], cuts, [n_rows]]).astype(int)


def sweep(V, M, W, g, active=None, threads=None):
    """One undamped Stefcal step for every solution: returns ``N_j / D_j`` (S, N) complex128.

    V, M must be Hermitian and W symmetric in the antenna axes (as :func:`to_matrix` makes
    them); only the upper triangles are read.
    """
    S, N = g.shape
    active = np.ones(S, bool) if active is None else np.asarray(active, bool)
    g = np.ascontiguousarray(g, np.complex128)
    threads = max(1, min(n_threads() if threads is None else threads, N))
    b = _upper_bounds(N, threads)
    num = np.zeros((threads, S, N), np.complex128)
    den = np.zeros((threads, S, N))
    if threads == 1:
        _sweep_upper(V, M, W, g, active, num[0], den[0], 0, N)
    else:
        list(_pool(threads).map(lambda k: _sweep_upper(V, M, W, g, active, num[k], den[k], b[k], b[k + 1]),
                                range(threads)))
    num, den = num.sum(0), den.sum(0)
    out = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return np.where(active[:, None], out, g)


def sweep_numpy(V, M, W, g):
    """The same step as :func:`sweep` in plain numpy (reference for tests and the benchmark)."""
    N = g.shape[1]
    Wd = W * (1 - np.eye(N))
    Z = M * np.conj(g)[:, None, None, :]
    num = np.einsum("skji,skji->sj", Wd * V, np.conj(Z))
    den = np.einsum("skji,skji->sj", Wd, (Z * np.conj(Z)).real)
    return np.where(den > 0, num / np.where(den > 0, den, 1), 0)


def residual_power(V, M, W, g, threads=None):
    """Per-antenna weighted residual power and number of terms, each (S, N)."""
    S, N = g.shape
    chi, cnt = np.zeros((S, N)), np.zeros((S, N))
    run_rows(_residual_power, N, (V, M, W, np.ascontiguousarray(g, np.complex128), chi, cnt), threads)
    return chi, cnt


@dataclass
class StefcalResult:
    """Solutions of :func:`stefcal` for S independent problems of N antennas.

    gains (S, N) complex; flags (S, N) bool (no data, not finite, or not converged);
    iterations (S,) and converged (S,); change (S,): the final ``||dg|| / ||g||``;
    antenna_change (S, N): the final ``|dg_j| / |g_j|``; antenna_iterations (S, N): the
    last iteration at which antenna j still changed by ``>= tol``; chi2 (S, N): weighted
    residual power per term (``sum w |r|^2 / n``, ~1 for ``w = 1/sigma^2``); ref_ant (S,).
    """

    gains: np.ndarray
    flags: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    change: np.ndarray
    antenna_change: np.ndarray
    antenna_iterations: np.ndarray
    chi2: np.ndarray
    ref_ant: np.ndarray


def stefcal(V, M, W, g0=None, *, tol=1e-5, max_iter=100, damping="half", ref_ant=None, threads=None,
            diagnostics=True, active=None):
    """Solve ``V ~ diag(g) M diag(g)^H`` for S independent solutions.

    Parameters
    ----------
    V, M : ndarray (S, K, N, N) complex
        Hermitian antenna matrices of data and model (only the upper triangles are read; build
        them with :func:`mmflow.calibrate.baselines.to_matrix`); the K samples (integrations x
        channels) of a solution are summed in the normal equations. Broadcast views are fine.
    W : ndarray (S, K, N, N) real, symmetric
        Weights, 0 = flagged; the diagonal (autocorrelations) is ignored. V must be finite
        (flagged samples may hold any finite value).
    g0 : ndarray (S, N) complex, optional
        Starting gains (default 1).
    tol, max_iter, damping : see the module docstring.
    ref_ant : int or None
        Phase reference antenna; ``None`` picks the antenna with most unflagged weight
        per solution. Pass ``-1`` to leave the phase as the iteration left it (peeling).
    diagnostics : bool
        False skips flags, chi2 and the phase reference (they are None): the lean call
        peeling makes many times per integration.
    active : bool array (S,), optional
        Solve only these solutions; the others keep ``g0`` and report 0 iterations (lets
        callers pass views instead of copying subsets).

    Returns
    -------
    StefcalResult
    """
    if damping not in DAMPING:
        raise InputError("calibration", "damping", f"unknown damping '{damping}'", f"use one of {DAMPING}")
    S, K, N, _ = V.shape
    g = np.ones((S, N), np.complex128) if g0 is None else np.array(g0, np.complex128, copy=True)
    active = np.ones(S, bool) if active is None else np.array(active, bool)
    iters = np.zeros(S, int)
    change = np.full(S, np.inf)
    ant_change = np.full((S, N), np.inf)
    ant_iter = np.zeros((S, N), int)

    def step(x):
        return sweep(V, M, W, x, active, threads)

    for it in range(1, max_iter + 1):
        if damping == "rk4":
            k1 = step(g) - g
            k2 = step(g + k1 / 2) - (g + k1 / 2)
            k3 = step(g + k2 / 2) - (g + k2 / 2)
            k4 = step(g + k3) - (g + k3)
            new = g + (k1 + 2 * k2 + 2 * k3 + k4) / 6
        else:
            new = step(g)
            if damping == "half" and it % 2 == 0:
                new = 0.5 * (new + g)
        dg = np.abs(new - g)
        norm = np.maximum(np.linalg.norm(g, axis=1), 1e-300)
        rel = np.linalg.norm(dg, axis=1) / norm
        a = active
        g[a] = new[a]
        iters[a] = it
        change[a] = rel[a]
        ant_change[a] = dg[a] / np.maximum(np.abs(g[a]), 1e-300)
        ant_iter[a] = np.where(ant_change[a] >= tol, it, ant_iter[a])
        active = active & ~(rel < tol)
        if not active.any():
            break
    converged = change < tol
    if not diagnostics:
        return StefcalResult(g, None, iters, converged, change, ant_change, ant_iter, None, None)
    wsum = np.abs(W).sum(axis=(1, 3)) - np.abs(np.diagonal(W, axis1=2, axis2=3)).sum(axis=1)
    flags = (wsum <= 0) | ~np.isfinite(g) | (g == 0)
    flags |= ~converged[:, None] & (ant_change >= tol * np.sqrt(N))
    g[flags] = 0.0
    chi, cnt = residual_power(V, M, W, g, threads)
    chi2 = np.where(cnt > 0, chi / np.maximum(cnt, 1), np.nan)
    if ref_ant is None:
        ref = np.argmax(np.where(flags, -1.0, wsum), axis=1)
    else:
        ref = np.full(S, int(ref_ant))
    if ref_ant != -1:
        gr = g[np.arange(S), ref]
        ph = np.where(np.abs(gr) > 0, np.conj(gr) / np.maximum(np.abs(gr), 1e-300), 1.0)
        g *= ph[:, None]
    return StefcalResult(g, flags, iters, converged, change, ant_change, ant_iter, chi2, ref)


def flag_outlier_antennas(V, M, W, result, *, n_sigma=5.0, lengths=None, **kwargs):
    """Flag every outlier antenna of each solution at once, re-solve without them, and judge again every
    antenna, the flagged ones included, until the flagged set no longer changes.

    The statistic (:mod:`mmflow.calibrate.outliers`) is built of medians and a low quantile over
    baselines, so that it holds while fewer than about a third of the antennas are bad and no good
    antenna is judged by the noise of the bad ones on its baselines:

        rho_ij = sum_k w_ijk |V_ijk - g_i M_ijk g_j^*|^2 / sum_k w_ijk
        f(b)   = lower quartile of rho over the baselines of length ~b (one bin without ``lengths``)
        x_i    = median_j rho_ij / f(|b_ij|),     outlier:  x_i > median(x) + n_sigma 1.4826 MAD(x)

    with ``j`` and the median and MAD over the unflagged antennas; a flagged antenna is judged with
    its gain against the unflagged ones (one Stefcal step, :func:`sweep`), so that an antenna
    flagged while the first solve was still pulled by the bad ones is let back once the solve no
    longer is. ``lengths`` (N, N): the baseline lengths (None: one bin). An antenna whose model leaves
    at most :data:`mmflow.calibrate.outliers.MAX_EXPLAINED_RESIDUAL` of its signal unexplained
    (``median_j r_ij / p_ij``) is never an outlier: direction-dependent errors of a modelled source,
    largest on the outermost antennas, flag no antenna, an antenna whose data do not follow the
    model does. The flagged antennas' weights are zeroed (``W`` is not modified) and the solutions
    whose set changed re-solved from the previous gains; the search stops when the set is unchanged
    or repeats, after N rounds at most (no cap below the array's size). Antennas the solve itself
    flags (no data, not converged) are not judged.
    Returns the new result and the weights.
    """
    W0, N = W, V.shape[2]
    search = np.zeros(result.flags.shape, bool)
    seen = {search.tobytes()}
    for _ in range(N):
        partners = ~result.flags
        g = result.gains.copy()
        s = np.flatnonzero(search.any(axis=1))
        if s.size:  # the flagged antennas' gains against the unflagged ones (others held): one step
            both = partners[s][:, None, :, None] | partners[s][:, None, None, :]
            step = sweep(V[s], M[s], W0[s] * both, g[s] + (g[s] == 0), threads=kwargs.get("threads"))
            g[s] = np.where(search[s], step, g[s])
        x, u = antenna_statistics(V, M, W0, g, partners, lengths)
        new = outliers(x, partners, u, n_sigma) & (partners | search)
        if (new == search).all():
            break
        repeats = new.tobytes() in seen  # a cycle: take this set and stop
        seen.add(new.tobytes())
        s = np.flatnonzero((new != search).any(axis=1))
        search = new
        keep = ~search[s]
        W = np.array(W0, copy=True) if W is W0 else W
        W[s] = W0[s] * (keep[:, None, :, None] & keep[:, None, None, :])
        sub = stefcal(V[s], M[s], W[s], g[s] + (g[s] == 0), **kwargs)
        for name in StefcalResult.__dataclass_fields__:
            getattr(result, name)[s] = getattr(sub, name)
        if repeats:
            break
    return result, W


@dataclass
class GainSolution:
    """Gains per solution interval, from :func:`solve_gains`.

    gains, flags, chi2, antenna_change, antenna_iterations: (n_interval, n_ant, n_pol);
    iterations, converged, change, ref_ant: (n_interval, n_pol); solint: integrations per
    interval (the last interval may be shorter).
    """

    gains: np.ndarray
    flags: np.ndarray
    chi2: np.ndarray
    antenna_change: np.ndarray
    antenna_iterations: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    change: np.ndarray
    ref_ant: np.ndarray
    solint: int


def dense_problem(vis, model, weights, pairs, n_ant, solint, baseline_keep=None):
    """Baseline-layout arrays -> Stefcal's (S, K, N, N) matrices.

    ``vis`` is (time, bl, pol) or (time, chan, bl, pol); ``model`` and ``weights`` broadcast
    to it. Solution s = interval * n_pol + pol; samples K = integrations x channels of the
    interval (the last interval is zero-padded with zero weight).
    """
    vis = np.asarray(vis)
    if vis.ndim not in (3, 4):
        raise InputError("visibilities", "shape", f"{vis.shape} is not (time, [chan,] bl, pol)",
                         "give visibilities shaped (time, bl, pol) or (time, chan, bl, pol)")
    model = np.broadcast_to(model, vis.shape)
    w = np.array(np.broadcast_to(weights, vis.shape), float)
    if vis.ndim == 3:
        vis, model, w = vis[:, None], model[:, None], w[:, None]
    pairs = check_pairs(pairs, n_ant)
    w[..., pairs[:, 0] == pairs[:, 1], :] = 0.0
    if baseline_keep is not None:
        w[..., ~np.asarray(baseline_keep, bool), :] = 0.0
    if np.any(~np.isfinite(vis) & (w > 0)):
        raise InputError("visibilities", "data", "NaN or inf in unflagged data",
                         "flag those samples (weight 0) before calibrating")
    T, C, B, P = vis.shape
    n_int = -(-T // solint)
    pad = n_int * solint - T

    def dense(x, dtype):
        x = np.nan_to_num(np.asarray(x, dtype)) if dtype != float else np.asarray(x, dtype)  # noqa: E721 (a numpy dtype equals float too)
        if pad:
            x = np.concatenate([x, np.zeros((pad,) + x.shape[1:], x.dtype)])
        x = x.reshape(n_int, solint * C, B, P)
        x = np.moveaxis(x, -1, 1).reshape(n_int * P, solint * C, B)
        return to_matrix(x, pairs, n_ant)

    cdt = complex_dtype(vis.dtype).type
    return dense(vis, cdt), dense(model, cdt), dense(w, np.float32 if cdt == np.complex64 else float)


def solve_gains(vis, model, weights, pairs, n_ant, *, solint=None, baseline_keep=None, tol=1e-5,
                max_iter=100, damping="half", ref_ant=None, outlier_sigma=5.0, g0=None, threads=None,
                baseline_lengths=None):
    """Direction-independent gains per solution interval and polarisation.

    Parameters
    ----------
    vis : ndarray (time, bl, pol) or (time, chan, bl, pol)
    model : ndarray broadcastable to ``vis``: model visibilities (sky through the beam)
    weights : ndarray broadcastable to ``vis``: 0 = flagged
    pairs : ndarray (n_bl, 2); n_ant : int
    solint : int, optional
        Integrations per solution (default: all of them in one solution).
    baseline_keep : bool array (n_bl,), optional
        Baselines to use, e.g. :func:`mmflow.calibrate.baselines.baseline_mask` (min length).
        Autocorrelations are always excluded.
    outlier_sigma : float or None
        Flag the outlier antennas at this many sigma, all at once, re-solving until none is left
        (:func:`flag_outlier_antennas`); None: off.
    g0 : ndarray (n_interval, n_ant, n_pol), optional starting gains.
    baseline_lengths : ndarray (n_bl,), optional
        Length of each pair (any unit): the outlier search then compares each antenna's residuals
        with the typical residuals at its baselines' lengths
        (:func:`mmflow.calibrate.outliers.antenna_statistics`), so that direction-dependent errors,
        largest on the longest baselines, flag no antenna.

    Returns
    -------
    GainSolution
    """
    T = np.shape(vis)[0]
    solint = T if solint is None else int(solint)
    V, M, W = dense_problem(vis, model, weights, pairs, n_ant, solint, baseline_keep)
    P = np.shape(vis)[-1]
    kw = dict(tol=tol, max_iter=max_iter, damping=damping, ref_ant=ref_ant, threads=threads)
    g0 = None if g0 is None else np.moveaxis(np.asarray(g0), -1, 1).reshape(-1, n_ant)
    res = stefcal(V, M, W, g0, **kw)
    if outlier_sigma is not None:
        lengths = None
        if baseline_lengths is not None:
            lengths = np.zeros((n_ant, n_ant))
            p = np.asarray(pairs)
            lengths[p[:, 0], p[:, 1]] = lengths[p[:, 1], p[:, 0]] = np.asarray(baseline_lengths, float)
        res, _ = flag_outlier_antennas(V, M, W, res, n_sigma=outlier_sigma, lengths=lengths, **kw)
    n_int = V.shape[0] // P

    def ant(x):
        return np.moveaxis(x.reshape(n_int, P, n_ant), 1, -1)

    return GainSolution(ant(res.gains), ant(res.flags), ant(res.chi2), ant(res.antenna_change),
                        ant(res.antenna_iterations), res.iterations.reshape(n_int, P),
                        res.converged.reshape(n_int, P), res.change.reshape(n_int, P),
                        res.ref_ant.reshape(n_int, P), solint)


def best_track(apparent_flux, n_int, weights=None):
    """The calibration track: the ``n_int`` consecutive integrations that maximise the
    smallest apparent flux of the calibrators (default recipe: Cyg A and Cas A both high,
    ~22 min = 100 integrations of 13 s). ``apparent_flux`` (n_src, n_time) from
    :func:`mmflow.calibrate.coherency.apparent_flux`; ``weights`` (n_time,) 0 excludes
    flagged integrations. Returns a slice.
    """
    f = np.min(np.asarray(apparent_flux, float), axis=0)
    if weights is not None:
        f = np.where(np.asarray(weights) > 0, f, -np.inf)
    T = len(f)
    n_int = min(int(n_int), T)
    win = np.lib.stride_tricks.sliding_window_view(f, n_int).min(axis=1)
    t0 = int(np.argmax(win))
    return slice(t0, t0 + n_int)


def gains_per_integration(solution, n_time):
    """Expand interval solutions to (time, n_ant, n_pol) gains and flags."""
    idx = np.minimum(np.arange(n_time) // solution.solint, len(solution.gains) - 1)
    return solution.gains[idx], solution.flags[idx]


__all__ = ["stefcal", "sweep", "solve_gains", "gains_per_integration",
           "best_track", "flag_outlier_antennas", "dense_problem", "StefcalResult", "GainSolution"]
