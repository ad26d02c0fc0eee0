"""Weighted least-squares m-modes: flagged and missing sidereal bins are not zeros.

Each baseline's drift scan is a trigonometric polynomial of the sidereal angle, band-limited
at the baseline's fringe band limit ``M_b`` (the sky holds no power beyond it)::

    V(phi) = sum_{|m| <= M_b} V_m exp(+i m phi)

The plain transform ``V_m = (1/N) sum_n V_n exp(-i m phi_n)`` recovers ``V_m`` exactly only
when every bin holds data; zero-filling a flagged bin subtracts that bin's share from every
``m`` (power scattered across m, and all m-modes scaled down by the coverage). Here the
m-modes of each baseline solve the weighted least-squares problem

    min_x  sum_{n filled} w_n |V_n - (F x)_n|^2 + g sum_{n empty} |P_n - (F x)_n|^2 + mu sum_m |x_m - p_m|^2

    (F x)_n = sum_{|m|<=M_b} x_m e^{i m phi_n}

with ``phi_n = 2 pi n / N + offset_n`` (the bins' exact sidereal angles), bin weights
``w_n >= 0`` (0 = no data), an optional prior ``p`` (default 0; e.g. the m-modes of a first-pass
map's model visibilities) and its model ``P = F p``. Empty bins are pseudo-observations of the
prior with weight ``g = sigma^2 / S`` (noise variance per unit weight over the sky's power per
bin, :func:`gap_weight`; 0 when ``sigma^2`` is not given): the data decide every direction they
measure above the noise, the prior the rest. ``mu = lambda * sum_n w_n`` (``lambda`` small,
default ``1e-6`` without ``sigma^2``, else 0) pulls every m towards the prior. With
``W' = W + g 1_empty`` the normal equations

    (A + mu I) x = F^H W' [V or P] + mu p,   A_{m m'} = c_{m - m'},   c_k = sum_n w'_n e^{-i k phi_n}

have a Hermitian Toeplitz matrix. They are solved by conjugate gradients for all baselines
of a chunk at once (per-baseline step lengths), the Toeplitz products by circulant embedding
(one forward and one inverse FFT of length ``>= 4 M + 1`` per iteration), with the diagonal
(Jacobi) preconditioner ``1 / (sum_n w'_n + mu)``: the diagonal of a Toeplitz matrix is constant,
so this only scales each baseline; what bounds the conditioning (and the iterations) is the
gap weight ``g``. With equal weights on the bin grid ``A = c_0 I``: one iteration, and the
result is the plain transform.
"""
from __future__ import annotations

from dataclasses import dataclass

import ducc0
import numpy as np
import scipy.fft

from mmflow.conventions import TWO_PI, m_slice
from mmflow.errors import InputError
from mmflow.mmode.engine import BaselineChunk, GridCache, chunk_grid
from mmflow.mmode.noise import baseline_coverage, lsq_inverse_variance, residual_variance
from mmflow.mmode.transfer import transfer_pass
from mmflow.mmode.transform import mmode_transform, split_bins, split_mmode_transform
from mmflow.threads import n_threads

NUFFT_EPS = 1e-13  # ducc0's finest double-precision accuracy (off-grid phases)
# ducc0's NUFFTs run on one thread: with several, the spreading sums in a thread-dependent order,
# and a run resumed with another thread budget (another cluster size) must give the same bits.
# Parallelism comes from the tasks (one per baseline chunk).


@dataclass
class LsqMmodes:
    """Result of :func:`lsq_mmodes` for one chunk of baselines (``n_bl`` columns).

    Attributes
    ----------
    mmodes : ndarray (mmax + 1, 2, n_bl) complex
        ``[m, 0] = V_m``, ``[m, 1] = conj(V_{-m})`` (``[0, 1] = 0``), zero for ``m > M_b``.
    band_limit : ndarray (n_bl,) int
        ``M_b`` fitted per baseline (may exceed ``mmax``).
    rss : ndarray (n_bl,)
        Weighted residual sum of squares ``sum_n w_n |V_n - model_n|^2``.
    n_filled : ndarray (n_bl,) int
        Bins with ``w_n > 0``.
    weight_sum : ndarray (n_bl,)
        ``sum_n w_n`` (the diagonal ``c_0`` of the normal matrix).
    signal_power : ndarray (n_bl,)
        ``sum_n w_n |V_n|^2 / n_filled``: the data's power per bin (for noise floors).
    iterations : ndarray (n_bl,) int
        Conjugate-gradient iterations each baseline took.
    converged : ndarray (n_bl,) bool
        ``||r|| <= tol ||b||`` reached within ``maxiter``.
    gap_weight : ndarray (n_bl,)
        Weight given to each empty bin as an observation of the prior model (0 without ``sigma2``).
    """

    mmodes: np.ndarray
    band_limit: np.ndarray
    rss: np.ndarray
    n_filled: np.ndarray
    weight_sum: np.ndarray
    signal_power: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    gap_weight: np.ndarray


def _phase_sums(values, k_max, offset, n):
    """``s_k = sum_n values_n e^{-i k phi_n}`` for ``k = -k_max..k_max``, shape ``(n_bl, 2 k_max + 1)``.

    ``values`` is ``(n_bl, N)``. On the bin grid an FFT (exact), else a type-1 NUFFT (ducc0).
    """
    if offset is None:
        spec = scipy.fft.fft(values, axis=-1, workers=n_threads())
        return spec[:, np.arange(-k_max, k_max + 1) % n]

    phi = TWO_PI * np.arange(n) / n + offset
    out = np.empty((values.shape[0], 2 * k_max + 1), np.complex128)
    ducc0.nufft.nu2u(points=np.ascontiguousarray(values, np.complex128), coord=phi[:, None], forward=True,
                     epsilon=NUFFT_EPS, nthreads=1, out=out)
    return out


def _synthesis(x, offset, n):
    """``model_n = sum_m x_m e^{+i m phi_n}`` for ``x`` of shape ``(n_bl, 2 M + 1)`` (m = -M..M)."""
    k_max = (x.shape[1] - 1) // 2
    if offset is None:
        grid = np.zeros((x.shape[0], n), np.complex128)
        grid[:, np.arange(-k_max, k_max + 1) % n] = x
        return scipy.fft.ifft(grid, axis=-1, workers=n_threads()) * n

    phi = TWO_PI * np.arange(n) / n + offset
    out = np.empty((x.shape[0], n), np.complex128)
    ducc0.nufft.u2nu(grid=np.ascontiguousarray(x), coord=phi[:, None], forward=False, epsilon=NUFFT_EPS,
                     nthreads=1, out=out)
    return out


class _Toeplitz:
    """``y = T x`` with ``T_{ij} = c_{i-j}`` (``i, j = 0..K-1``) per row of a batch, by circulant embedding."""

    def __init__(self, c, k):
        # c: (n_bl, 2K - 1) holding c_{-(K-1)} .. c_{K-1}
        self.k = k
        self.size = scipy.fft.next_fast_len(2 * k - 1)
        col = np.zeros((c.shape[0], self.size), np.complex128)
        col[:, :k] = c[:, k - 1:]  # c_0 .. c_{K-1}
        col[:, self.size - (k - 1):] = c[:, :k - 1]  # c_{-(K-1)} .. c_{-1}
        self.spec = scipy.fft.fft(col, axis=-1, workers=n_threads())

    def __call__(self, x):
        w = n_threads()
        xf = scipy.fft.fft(x, n=self.size, axis=-1, workers=w)
        return scipy.fft.ifft(xf * self.spec, axis=-1, workers=w)[:, :self.k]


def _to_layout(x, mmax, k_max):
    """Internal ``(n_bl, 2 k_max + 1)`` (m = -k_max..k_max) -> ``(mmax + 1, 2, n_bl)`` (|m| > mmax dropped)."""
    out = np.zeros((mmax + 1, 2, x.shape[0]), np.complex128)
    kk = min(k_max, mmax)
    out[:kk + 1, 0] = x[:, k_max:k_max + kk + 1].T
    out[:kk + 1, 1] = np.conj(x[:, k_max - kk:k_max + 1][:, ::-1]).T
    out[0, 1] = 0
    return out


def _from_layout(mm, k_max):
    """``(mmax + 1, 2, n_bl)`` -> internal ``(n_bl, 2 k_max + 1)`` (zero beyond mmax)."""
    x = np.zeros((mm.shape[2], 2 * k_max + 1), np.complex128)
    kk = min(k_max, mm.shape[0] - 1)
    x[:, k_max:k_max + kk + 1] = mm[:kk + 1, 0].T
    x[:, k_max - kk:k_max] = np.conj(mm[kk:0:-1, 1]).T
    return x


def gap_weight(sigma2, signal_power, n_filled, weight_sum):
    """Weight of an empty bin as a pseudo-observation of the prior model: ``sigma^2 / S``.

    ``S = (sum_n w_n |V_n|^2 - N_filled sigma^2) / sum_n w_n`` is the sky's power per bin (the
    data's power less the noise's, ``E[w_n |V_n|^2] = w_n |s_n|^2 + sigma^2``): the prior's
    error in a gap is taken to be as large as the signal itself. High signal-to-noise: small
    weights, the data decide all they measure; low: the gaps hold the prior, and noise is
    not amplified into the directions the data barely constrain (a Wiener filter restricted
    to the gaps). Capped at the mean weight of a filled bin, ``sum w / N_filled`` (a
    pseudo-observation never outweighs a real one; at the cap, noise-dominated data, the fit
    tends to the zero-filled transform); 0 where ``sigma^2 = 0`` or unknown.
    """
    sigma2 = np.nan_to_num(np.asarray(sigma2, float), nan=0.0, posinf=0.0)
    n_filled = np.asarray(n_filled, float)
    total = np.asarray(signal_power, float) * n_filled  # sum w |V|^2
    sky = total - n_filled * sigma2
    ws = np.asarray(weight_sum, float)
    cap = ws / np.maximum(n_filled, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(sky > 0, sigma2 * ws / np.where(sky > 0, sky, 1), np.inf)
    return np.where(sigma2 > 0, np.minimum(g, cap), 0.0)


def lsq_mmodes(binned, bin_weight, mmax, band_limit=None, offset=None, sigma2=None, regularization=None,
               prior=None, tol=1e-10, maxiter=None):
    """Weighted least-squares m-modes of sidereally binned data (see the module docstring).

    Parameters
    ----------
    binned : ndarray (N, n_bl) complex
        Sidereal bins (:func:`mmflow.mmode.transform.sidereal_bins`); values of empty bins are ignored.
    bin_weight : ndarray (N, n_bl)
        Inverse-variance weight of each bin up to one factor per baseline (summed sample
        weights from ``sidereal_bins``); 0 = no data.
    mmax : int
        Size of the output's m axis; ``N >= 2 max(M_b) + 1``.
    band_limit : int or ndarray (n_bl,), optional
        ``M_b``: the fit holds ``|m| <= M_b`` only (default ``mmax``). Give the band limit of
        the *visibilities*, e.g. ``Telescope.baseline_lmax(freq_hz, (N - 1) // 2, pairs)``:
        it may exceed ``mmax`` (a sky with power beyond the imaging lmax), in which case
        ``|m| > mmax`` are fitted, so that flags do not fold them into the kept ones, and dropped.
    offset : ndarray (N,), optional
        ``phi_n - 2 pi n / N`` from ``sidereal_bins``: the exact phases (type-1/2 NUFFT, accurate
        to ~1e-12) instead of the grid (FFT).
    sigma2 : float or ndarray (n_bl,), optional
        Noise variance per unit weight (``Var(V_n) = sigma^2 / w_n``), e.g. from
        :func:`mmflow.mmode.noise.radiometer_variance`. When given, every empty bin becomes a
        pseudo-observation of the prior model (0 without a prior) with weight
        :func:`gap_weight` ``= sigma^2 / S``: noise-aware regularisation of the gaps only.
        ``"residual"``: estimate it first from an unweighted-gap fit
        (:func:`mmflow.mmode.noise.residual_variance`; twice the cost), for data without
        autocorrelations.
    regularization : float or ndarray (n_bl,), optional
        ``lambda`` in ``mu = lambda * sum_n w_n`` (pulls every m towards the prior). Default
        ``1e-6`` without ``sigma2`` (for long gaps), 0 with it. With equal weights and no
        gaps the result is ``(V_m^plain + lambda p_m) / (1 + lambda)``.
    prior : ndarray (mmax + 1, 2, n_bl), optional
        m-modes the regularisation pulls towards (and the starting point), in the output
        layout: e.g. the m-modes of a first-pass map's model visibilities.
    tol : float
        Stop a baseline when ``||b - (A + mu) x|| <= tol ||b||``.
    maxiter : int, optional
        Iteration cap (default ``2 max(M_b) + 1``, where CG is exact in exact arithmetic).

    Returns
    -------
    LsqMmodes
    """
    binned = np.asarray(binned)
    w = np.asarray(bin_weight, float)
    if binned.ndim != 2 or w.shape != binned.shape:
        raise InputError("least-squares m-modes", "binned", f"shapes {binned.shape} and {w.shape}",
                         "pass (n_bins, n_baselines) bins and weights of the same shape")
    n, n_bl = binned.shape
    if np.any(w < 0) or not np.all(np.isfinite(w)):
        raise InputError("least-squares m-modes", "bin_weight", "negative or non-finite weights",
                         "weights must be finite and >= 0 (0 = no data)")
    mb = np.full(n_bl, mmax, int) if band_limit is None else np.broadcast_to(np.asarray(band_limit, int), (n_bl,))
    if np.any(mb < 0):
        raise InputError("least-squares m-modes", "band_limit", f"negative band limit {mb.min()}",
                         "give each baseline's fringe band limit (>= 0)")
    if n < 2 * int(mb.max(initial=0)) + 1:
        raise InputError("m-mode transform", "n_bins", f"{n} sidereal bins cannot resolve band limit "
                         f"{int(mb.max())} (mmax={mmax})",
                         f"use at least {2 * int(mb.max()) + 1} bins (or lower mmax)")
    if offset is not None:
        offset = np.asarray(offset, float)
        offset = offset if np.any(offset) else None
    if isinstance(sigma2, str):
        if sigma2 != "residual":
            raise InputError("least-squares m-modes", "sigma2", f"unknown estimator '{sigma2}'",
                             "pass variances, None or 'residual'")
        sigma2 = estimate_sigma2(binned, w, mmax, mb, offset)
    if regularization is None:
        regularization = 1e-6 if sigma2 is None else 0.0
    k_max = int(mb.max()) if n_bl else 0
    k = 2 * k_max + 1
    filled = w > 0
    data = np.where(filled, binned, 0)
    c0 = w.sum(axis=0)
    n_filled = filled.sum(axis=0)
    power = np.sum(w * np.abs(data) ** 2, axis=0) / np.maximum(n_filled, 1)
    mask = (np.abs(np.arange(-k_max, k_max + 1))[None, :] <= mb[:, None]) & (c0 > 0)[:, None]
    x0 = None if prior is None else _from_layout(np.asarray(prior), k_max) * mask

    # empty bins as pseudo-observations of the prior model, weighted by sigma^2 / S
    gw = np.zeros(n_bl) if sigma2 is None else gap_weight(np.broadcast_to(sigma2, (n_bl,)), power, n_filled, c0)
    w_eff = w + gw[None, :] * ~filled
    target = data if x0 is None else np.where(filled, data, _synthesis(x0, offset, n).T)
    mu = np.asarray(regularization, float) * c0
    diag = w_eff.sum(axis=0) + mu
    inv_diag = np.where(diag > 0, 1 / np.where(diag > 0, diag, 1), 0.0)[:, None]

    toeplitz = _Toeplitz(_phase_sums(np.ascontiguousarray(w_eff.T).astype(np.complex128), 2 * k_max, offset, n), k)
    rhs = _phase_sums(np.ascontiguousarray((target * w_eff).T), k_max, offset, n) * mask
    x = np.zeros((n_bl, k), np.complex128) if x0 is None else x0.copy()
    if x0 is not None:
        rhs = rhs + mu[:, None] * x0

    def matvec(v):
        return (toeplitz(v) + mu[:, None] * v) * mask

    x, iters, converged = _pcg(matvec, rhs, x, inv_diag, tol, k if maxiter is None else int(maxiter))
    model = _synthesis(x, offset, n).T  # (N, n_bl)
    rss = np.sum(w * np.abs(np.where(filled, binned - model, 0)) ** 2, axis=0)
    return LsqMmodes(_to_layout(x, mmax, k_max), mb.copy(), rss, n_filled, c0, power, iters,
                     converged | (c0 == 0), gw)


def _pcg(matvec, rhs, x, inv_diag, tol, maxiter):
    """Jacobi-preconditioned conjugate gradients, one independent system per row, step lengths per row."""
    r = rhs - matvec(x) if np.any(x) else rhs.copy()
    bnorm = np.linalg.norm(rhs, axis=1)
    z = r * inv_diag
    p = z.copy()
    rz = np.real(np.sum(np.conj(r) * z, axis=1))
    iters = np.zeros(len(x), int)
    active = np.linalg.norm(r, axis=1) > tol * bnorm
    while np.any(active) and iters.max(initial=0) < maxiter:
        ap = matvec(p)
        pap = np.real(np.sum(np.conj(p) * ap, axis=1))
        alpha = np.where(active & (pap > 0), rz / np.where(pap > 0, pap, 1), 0.0)
        x += alpha[:, None] * p
        r -= alpha[:, None] * ap
        z = r * inv_diag
        rz_new = np.real(np.sum(np.conj(r) * z, axis=1))
        beta = np.where(active & (rz > 0), rz_new / np.where(rz > 0, rz, 1), 0.0)
        p = z + beta[:, None] * p
        rz = rz_new
        iters += active
        active &= (np.linalg.norm(r, axis=1) > tol * bnorm) & (pap > 0)
    converged = np.linalg.norm(r, axis=1) <= tol * np.maximum(bnorm, np.finfo(float).tiny)
    return x, iters, converged


def zero_filled_error(binned, bin_weight, mmax, reference, offset=None):
    """Relative rms per baseline of today's zero-filled transform against ``reference`` m-modes.

    ``||T(V 1_{w>0}) - reference|| / ||reference||`` with ``T`` the plain transform: the error
    that flagged time makes when it is treated as zeros (for reports and benchmarks).
    """
    zf = mmode_transform(np.where(np.asarray(bin_weight) > 0, binned, 0), mmax, offset)
    return relative_rms(zf, reference)


def relative_rms(mmodes, reference):
    """``||mmodes - reference|| / ||reference||`` per baseline (last axis) over all m and both signs."""
    d = np.asarray(mmodes) - np.asarray(reference)
    axes = tuple(range(d.ndim - 1))
    return np.sqrt(np.sum(np.abs(d) ** 2, axis=axes) / np.sum(np.abs(reference) ** 2, axis=axes))


def split_lsq_mmodes(binned, bin_weight, mmax, offset=None, splits=("full",), band_limit=None, **kw):
    """Least-squares m-modes of splits of the bins (as :func:`mmflow.mmode.transform.split_mmode_transform`).

    ``full`` fits every bin; ``even`` / ``odd`` fit bins ``2k`` / ``2k + 1`` at their own phases
    ``2 pi (2k + s) / N + offset``. Returns ``(mmodes (n_split, mmax + 1, 2, n_bl), results)`` with
    one :class:`LsqMmodes` per split (the ``full`` one carries the residuals for the noise).
    Keyword arguments go to :func:`lsq_mmodes`.
    """
    results = [lsq_mmodes(binned[rows], bin_weight[rows], mmax, band_limit, phase, **kw)
               for rows, phase in split_bins(binned.shape[0], offset, splits)]
    return np.stack([r.mmodes for r in results]), results


def estimate_sigma2(binned, bin_weight, mmax, band_limit=None, offset=None):
    """Per-sample noise variance per baseline from the residual of a first fit (no gap weights).

    :func:`mmflow.mmode.noise.residual_variance` of :func:`lsq_mmodes` with ``lambda = 1e-6``
    and ``tol = 1e-6`` (the residual on the filled bins converges long before the directions
    the gaps leave open), floored at ``1e-6`` of the chunk's largest signal power.
    """
    first = lsq_mmodes(binned, bin_weight, mmax, band_limit, offset, None, 1e-6, None, 1e-6)
    return residual_variance(first.rss, first.n_filled, first.band_limit, first.signal_power)


@dataclass
class ChunkMmodes:
    """What the ``mmodes`` stage stores for one chunk and frequency (see :func:`chunk_mmodes`).

    Attributes
    ----------
    mmodes : ndarray (n_split, mmax + 1, 2, n_bl)
    inv_var : ndarray (n_bl,)
        ``1 / Var(V_m)`` with the coverage factor (0 = unusable).
    sigma2 : ndarray (n_bl,)
        Per-sample noise variance used (given or estimated from the residual).
    coverage : mmflow.mmode.noise.Coverage
    fits : list of LsqMmodes
        One per split (iterations, convergence, residuals).
    """

    mmodes: np.ndarray
    inv_var: np.ndarray
    sigma2: np.ndarray
    coverage: object
    fits: list


def chunk_mmodes(binned, bin_weight, mmax, offset=None, band_limit=None, splits=("full",), sigma2=None,
                 min_coverage=0.0, coverage_policy="drop", tol=1e-10, prior=None):
    """m-modes, noise and coverage of one chunk of baselines at one frequency.

    1. ``sigma2`` (per sample, e.g. :func:`mmflow.mmode.noise.radiometer_variance`), or when
       None :func:`estimate_sigma2` from the residual of a first fit;
    2. :func:`split_lsq_mmodes` with that ``sigma2`` (gap pseudo-observations weighted
       ``sigma^2 / S``);
    3. :func:`mmflow.mmode.noise.baseline_coverage` (``drop`` / ``downweight`` below
       ``min_coverage``) and ``inv_var = factor * sum_n w_n / sigma^2``
       (:func:`mmflow.mmode.noise.lsq_inverse_variance`).

    ``prior``: m-modes ``(mmax + 1, 2, n_bl)`` of a previous map's model (:func:`prior_mmodes`)
    for every split.
    """
    w = np.asarray(bin_weight, float)
    if sigma2 is not None and prior is None and _uniform_on_grid(w, offset):
        # every bin filled with equal weight on the bin grid: the least-squares fit is the plain
        # transform (to 1e-12, tests/unit/mmode/test_gapfill.py) -- take it directly (one FFT per split)

        sigma2 = np.broadcast_to(np.asarray(sigma2, float), (binned.shape[1],)).copy()
        mm = split_mmode_transform(binned, mmax, None, splits)
        cov = baseline_coverage(w, min_coverage, coverage_policy)
        return ChunkMmodes(mm, lsq_inverse_variance(sigma2, w.sum(axis=0), cov), sigma2, cov, [])
    if sigma2 is None:
        sigma2 = estimate_sigma2(binned, bin_weight, mmax, band_limit, offset)
    sigma2 = np.broadcast_to(np.asarray(sigma2, float), (binned.shape[1],)).copy()
    mm, fits = split_lsq_mmodes(binned, bin_weight, mmax, offset, splits, band_limit, sigma2=sigma2, tol=tol,
                                prior=prior)
    cov = baseline_coverage(bin_weight, min_coverage, coverage_policy)
    inv_var = lsq_inverse_variance(sigma2, np.asarray(bin_weight, float).sum(axis=0), cov)
    return ChunkMmodes(mm, inv_var, sigma2, cov, fits)


def _uniform_on_grid(bin_weight, offset):
    """True when every bin of every baseline holds data with one weight, on the bin grid."""
    return (bin_weight.size > 0 and bool(np.all(bin_weight == bin_weight.flat[0])) and bin_weight.flat[0] > 0
            and (offset is None or not np.any(offset)))


def longest_gap(bin_weight):
    """The longest run of empty sidereal bins (``w_n = 0``) per baseline, the bins taken as a circle
    (a gap across ``phi = 0`` is one gap): shape ``(n_bl,)``; ``N`` for a baseline without data.

    ``bin_weight``: ``(N, n_bl)`` as for :func:`lsq_mmodes`. With ``last_n`` the latest filled bin at or
    before ``n`` (a running maximum), the runs end at ``n - last_n``; the gap across ``phi = 0`` is
    ``first + N - 1 - last`` (the first and last filled bins).
    """
    filled = np.asarray(bin_weight) > 0
    n = filled.shape[0]
    idx = np.arange(n)[:, None]
    last = np.maximum.accumulate(np.where(filled, idx, -1), axis=0)
    inner = np.max(idx - last, axis=0, initial=0)
    first = np.argmax(filled, axis=0)
    wrap = first + n - 1 - last[-1]
    return np.where(filled.any(axis=0), np.maximum(inner, wrap), n)


def unbridged_gaps(bin_weight, band_limit):
    """Which baselines have a gap their band limit cannot bridge: a run of empty bins longer than one
    Nyquist interval of the band-limited drift scan,

        G_b > N / (2 M_b + 1),

    ``G_b`` the longest gap (:func:`longest_gap`), ``M_b`` the band limit, ``N`` the bins. A shorter
    gap lies between samples as close as the band limit needs: :func:`lsq_mmodes` recovers the
    m-modes from the baseline's own data (5 % random flags: 1e-6, ``docs/mmodes.md``); in a longer one
    the drift scan is not in the baseline's data and only a map's prior fills it. Baselines without
    data are not counted (they are dropped). Returns a boolean array ``(n_bl,)``.
    """
    w = np.asarray(bin_weight)
    gap = longest_gap(w)
    mb = np.broadcast_to(np.asarray(band_limit, float), gap.shape)
    return (gap * (2 * mb + 1) > w.shape[0]) & np.any(w > 0, axis=0)


def refit_prior_m0(prior, binned, bin_weight, offset=None):
    """The prior with its ``m = 0`` term fitted to the data: the map's model for ``m != 0`` plus the constant
    that best matches the filled bins,

        p_0 = sum_n w_n (V_n - sum_{m != 0} p_m e^{i m phi_n}) / sum_n w_n.

    A map's model ``B_0 a_0`` is no model of a baseline's ``m = 0``: the imaging solve drops
    ``m = 0`` (``imaging.filter_m0``, the paper's default) and zeroes the monopole. Left so, the
    prior would put ``-V_0`` into every gap (its effect on the faint-source peak shift of
    ``tests/workflow/test_gap_prior_workflow.py``: ``docs/performance.md``).

    Parameters
    ----------
    prior : ndarray (K + 1, 2, n_bl)
        Prior m-modes in the layout of :func:`lsq_mmodes` (e.g. :func:`prior_mmodes`).
    binned, bin_weight, offset
        As for :func:`lsq_mmodes` (the bins of the fit the prior is for).

    Returns
    -------
    ndarray, a copy of ``prior`` with ``[0, 0]`` replaced (``p_0 = 0`` where no bin is filled).
    """
    w = np.asarray(bin_weight, float)
    out = np.array(prior, np.complex128)
    out[0] = 0
    n = w.shape[0]
    offset = None if offset is None or not np.any(offset) else np.asarray(offset, float)
    model = _synthesis(_from_layout(out, out.shape[0] - 1), offset, n).T  # (N, n_bl), m != 0 only
    ws = w.sum(axis=0)
    resid = np.sum(np.where(w > 0, w * (np.asarray(binned) - model), 0), axis=0)
    out[0, 0] = np.where(ws > 0, resid / np.where(ws > 0, ws, 1), 0)
    return out


def prior_mmodes(telescope, freq_hz, alm, lmax, baselines, mmax=None, dtype=np.float64, chunk_size=32):
    """m-modes of a map's model visibilities, ``v_m = B_m a_m``: the ``prior`` of :func:`lsq_mmodes`.

    Iterating map -> ``prior_mmodes`` -> ``lsq_mmodes(..., prior=...)`` -> map fills the
    directions a baseline's gaps leave open with what the other baselines saw (on simulated
    20 % block flags the peaks settle within 0.02 FWHM of the unflagged map's in 1-3 passes,
    see ``tests/workflow/test_mmode_gaps_map.py``).

    Parameters
    ----------
    telescope : mmflow.telescope.Telescope
    freq_hz : float
    alm : ndarray, healpy layout (Jy/sr, frame of date), band limit ``lmax``
    baselines : ndarray of int
        Indices into ``telescope.antenna_pairs()`` (the chunk's columns).
    mmax : int, optional (default ``lmax``)
    chunk_size : int
        Baselines per transfer-matrix block (by band limit, one quadrature grid shared): memory
        ``~ chunk_size * lmax^2 * 16 B`` as in the transfer stage, whatever the number of baselines.

    Returns
    -------
    ndarray (mmax + 1, 2, n_bl) complex, the layout of :func:`lsq_mmodes`.
    """
    mmax = lmax if mmax is None else mmax
    index = np.asarray(baselines, int)
    lmax_b = telescope.baseline_lmax(freq_hz, lmax)
    out = np.zeros((mmax + 1, 2, len(index)), np.complex128)
    order = np.argsort(lmax_b[index], kind="stable")  # like band limits share a grid
    cache = GridCache(telescope, freq_hz)
    step = max(1, int(chunk_size))
    for start in range(0, len(index), step):
        cols = order[start:start + step]
        chunk = BaselineChunk(index[cols], int(lmax_b[index[cols]].max()))
        b, grid = chunk_grid(telescope, freq_hz, chunk, lmax, cache)

        def model(m, blk, tim):  # blk[l - m, c]: B_m's column c (+m rows, then -m rows), l <= chunk.lmax
            return alm[m_slice(lmax, m)][:blk.shape[0]] @ blk

        v = transfer_pass(grid, b, model, lmax_b[chunk.index], min(mmax, chunk.lmax), dtype, chunk.lmax)
        for m, vm in enumerate(v):  # m beyond the chunk's band limit: B_m = 0
            out[m, 0, cols] = vm[:len(cols)]
            if m > 0:
                out[m, 1, cols] = vm[len(cols):]
    return out
