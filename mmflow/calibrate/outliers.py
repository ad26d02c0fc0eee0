"""Outlier antennas of a gain solution: a statistic that tolerates many bad antennas at once.

An antenna holding noise (a dead or miswired input) leaves its noise in the residuals of every
baseline it is on, so a sum over an antenna's baselines (its ``chi2``) mixes the noise of the bad
antennas into the good ones': with 13 of 42 antennas noisy, a good antenna's ``chi2`` is about a
third of a bad one's, the typical residual at a length (a median over baselines, half of them
noisy) is the noise's, and a threshold at ``median + 5 MAD`` over the array finds few of them.
Here every step is a median or a low quantile over baselines, each of which holds a minority of
noisy values while fewer than about a third of the antennas are bad (a fraction ``q`` of bad
antennas spoils ``1 - (1 - q)^2`` of the baselines, 51 % at ``q = 0.3``, and a fraction ``q`` of each
good antenna's baselines):

* per baseline the residual power per weight ``rho_ij = r_ij / w_ij`` with
  ``r_ij = sum_k w_ijk |V_ijk - g_i M_ijk g_j^*|^2``, ``w_ij = sum_k w_ijk``,
  and the model power ``p_ij = sum_k w_ijk |g_i M_ijk g_j^*|^2``;
* the typical residual at a baseline length ``f(b)``: the baselines between unflagged antennas cut
  into ``n_bins`` bins of equal count by length, :data:`TYPICAL_QUANTILE` (the lower quartile) of
  ``rho`` in each bin. Direction-dependent errors of a modelled source grow with baseline length;
  comparing each baseline with baselines of its length keeps the outermost antennas (whose
  baselines are all long) from being the array's largest residuals. The lower quartile stays among
  the clean baselines while noisy ones are fewer than 75 % of a bin (``q`` below a half);
* per antenna ``x_i = median_j rho_ij / f(|b_ij|)`` over its baselines to unflagged antennas (~1 for
  any antenna whose residuals are those of most baselines of its lengths, large for one whose
  baselines are all noisy, at most a fraction ``q < 1/2`` of a good antenna's baselines being
  noisy) and ``u_i = median_j r_ij / p_ij`` (the fraction of its signal the model leaves
  unexplained; ~1 or more for data that do not follow the model at all);
* an antenna is an outlier when ``x_i > median(x) + n_sigma 1.4826 MAD(x)`` (the median and MAD over
  the unflagged antennas: those of the good majority) and ``u_i > MAX_EXPLAINED_RESIDUAL`` (an
  antenna the model describes to within a quarter of its power is never one, whatever its
  residuals' rank: the direction-dependent errors of a modelled source flag no antenna).

All outliers of a solution are flagged at once, then the solution is re-solved without them and
searched again (:func:`mmflow.calibrate.stefcal.flag_outlier_antennas`). numpy only.
"""
from __future__ import annotations

import numpy as np

#: an antenna whose data the model describes to within this fraction of its model power is never an outlier
MAX_EXPLAINED_RESIDUAL = 0.25
#: the quantile of the baselines' residual power at a length taken as its typical value
TYPICAL_QUANTILE = 0.25
#: the fewest baselines per length bin (fewer bins on a small array)
MIN_PER_BIN = 8
#: MAD (in units of the statistic, ~1 for a good antenna) below which the spread is noiseless data's round-off
MAD_FLOOR = 1e-9
#: antenna-matrix elements of the samples :func:`baseline_residuals` takes at a time (its temporaries: ~16 MB each)
RESIDUAL_BLOCK_ELEMENTS = 2 ** 20


def baseline_residuals(V, M, W, gains):
    """``r``, ``p``, ``w`` (S, N, N) symmetric: per baseline the weighted residual power, model power and
    weight summed over the samples (module docstring); the diagonal of ``w`` is 0.

    ``V``, ``M``, ``W`` (S, K, N, N) as :func:`mmflow.calibrate.stefcal.stefcal` takes them, ``gains`` (S, N).
    Either triangle may hold the data (both are summed).
    """
    S, K, N, _ = V.shape
    r, p, w = np.zeros((S, N, N)), np.zeros((S, N, N)), np.zeros((S, N, N))
    block = max(1, RESIDUAL_BLOCK_ELEMENTS // (N * N))
    for s in range(S):
        g = gains[s].astype(np.complex128)
        for k0 in range(0, K, block):  # samples a block at a time (temporaries ~16 MB), summed in order
            ks = slice(k0, k0 + block)
            m = g[None, :, None] * M[s, ks] * np.conj(g)[None, None, :]
            res = V[s, ks] - m
            for rk, pk in zip(W[s, ks] * (res.real ** 2 + res.imag ** 2), W[s, ks] * (m.real ** 2 + m.imag ** 2)):
                r[s] += rk
                p[s] += pk
        w[s] = W[s].sum(axis=0, dtype=float)
    r, p, w = r + np.swapaxes(r, 1, 2), p + np.swapaxes(p, 1, 2), w + np.swapaxes(w, 1, 2)
    w[:, np.arange(N), np.arange(N)] = 0.0
    return r, p, w


def antenna_statistics(V, M, W, gains, partners, lengths=None, n_bins=16):
    """Each antenna's residuals over the typical residuals at its baselines' lengths, ``x``, and the
    fraction of its model power left unexplained, ``u`` (module docstring), each (S, N), over its
    baselines to the ``partners`` (S, N) bool (the unflagged antennas); the typical residual ``f(b)``
    from the baselines between partners. NaN for an antenna without a weighted baseline to a partner.

    ``gains`` (S, N): those of the solve, and for an antenna outside the partners its gain against
    them, so that a flagged antenna is judged as the others are. ``lengths`` (N, N), any unit; None
    compares every baseline with the whole array's (one bin).
    """
    S, K, N, _ = V.shape
    r, p, w = baseline_residuals(V, M, W, gains)
    iu = np.triu_indices(N, 1)
    lengths = np.zeros((N, N)) if lengths is None else np.asarray(lengths, float)
    x, u = np.full((S, N), np.nan), np.full((S, N), np.nan)
    for s in range(S):
        ok = np.asarray(partners[s], bool)
        use = (w[s] > 0) & ok[None, :]  # antenna i (row) against partner j
        sel = (use & ok[:, None])[iu]
        if not sel.any():
            continue
        rho = r[s] / np.where(use, w[s], 1.0)
        lb, rb = lengths[iu][sel], rho[iu][sel]
        bins = max(1, min(n_bins, lb.size // MIN_PER_BIN))
        edges = np.quantile(lb, np.linspace(0.0, 1.0, bins + 1))
        typical = binned_quantiles(rb, np.clip(np.searchsorted(edges, lb, side="right") - 1, 0, bins - 1), bins,
                                   TYPICAL_QUANTILE)
        typical = np.where(np.isfinite(typical), typical, np.nanmedian(typical))
        power = np.sum(W[s] * np.abs(V[s]) ** 2) / max(np.count_nonzero(W[s]), 1)
        f = np.maximum(typical[np.clip(np.searchsorted(edges, lengths, side="right") - 1, 0, bins - 1)], 1e-9 * power)
        has = use.any(axis=1)
        x[s, has] = np.nanmedian(np.where(use, rho / f, np.nan)[has], axis=1)
        u[s, has] = np.nanmedian(np.where(use, r[s] / np.maximum(p[s], 1e-300), np.nan)[has], axis=1)
    return x, u


def outliers(x, reference, u=None, n_sigma=5.0):
    """``x_i > median(x) + n_sigma 1.4826 MAD(x)`` per solution (rows of ``x`` (S, N); NaN: not judged),
    the median and MAD over the ``reference`` (S, N) antennas, the MAD floored at :data:`MAD_FLOOR`
    (noiseless data flag nothing), and, with ``u``, ``u_i > MAX_EXPLAINED_RESIDUAL``. Returns (S, N) bool."""
    x = np.asarray(x, float)
    ref = np.where(np.asarray(reference, bool) & np.isfinite(x), x, np.nan)
    rows = np.isfinite(ref).any(axis=1)
    med, mad = np.full(len(x), np.inf), np.full(len(x), np.inf)
    med[rows] = np.nanmedian(ref[rows], axis=1)
    mad[rows] = 1.4826 * np.nanmedian(np.abs(ref[rows] - med[rows, None]), axis=1)
    out = np.isfinite(x) & (x > (med + n_sigma * np.maximum(mad, MAD_FLOOR))[:, None])
    if u is not None:
        out &= ~(np.asarray(u) <= MAX_EXPLAINED_RESIDUAL)
    return out


def binned_quantiles(values, bins, n_bins, q=0.5):
    """``np.quantile(values[bins == b], q)`` (linear interpolation) for ``b = 0..n_bins-1`` (NaN for an
    empty bin, or one holding a NaN) from one sort; ``q=0.5`` is the median (the mean of the two
    middle values for an even count)."""
    v = values[np.lexsort((values, bins))]
    counts = np.bincount(bins, minlength=n_bins)
    if not len(v):
        return np.full(n_bins, np.nan)
    start = np.cumsum(counts) - counts
    filled = counts > 0
    pos = q * np.maximum(counts - 1, 0)
    lo = np.where(filled, start + np.floor(pos).astype(int), 0)
    hi = np.where(filled, start + np.ceil(pos).astype(int), 0)
    frac = pos - np.floor(pos)
    with_nan = np.bincount(bins, weights=np.isnan(values), minlength=n_bins) > 0
    return np.where(filled & ~with_nan, v[lo] + frac * (v[hi] - v[lo]), np.nan)


__all__ = ["antenna_statistics", "outliers", "baseline_residuals", "binned_quantiles", "MAX_EXPLAINED_RESIDUAL"]
