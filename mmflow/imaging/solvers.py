"""Regularised solutions of one m block from its normal equations (paper section 2.3).

All solvers take the (full, Hermitian) Gram ``G = B^H N^-1 B`` and ``r = B^H N^-1 v``:

* Tikhonov / minimum variance: ``a = (G + eps I)^-1 r`` via the Cholesky factor of
  ``G + eps I`` (minimum variance when G was accumulated with ``N^-1`` weights).
* Moore-Penrose: ``a = V diag(1/s_i, s_i > t^2) V^H r`` with ``G = V diag(s) V^H``,
  ``s_i = sigma_i^2``; singular values ``sigma_i <= t`` are dropped.
* With a prior: ``a = (G + eps I)^-1 (r - G a_prior) + a_prior``.
* Generalised: ``a = (G + eps A^H A)^-1 r``; ``A^H A = diag(l(l+1))`` penalises the gradient
  ``||grad I||^2 = sum l(l+1) |a_lm|^2`` (smoothness).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.linalg as sla
from scipy.linalg import lapack

from mmflow.conventions import m_slice, n_alm
from mmflow.errors import InputError
from mmflow.imaging.filters import filter_mask
from mmflow.imaging.lcurve import hermitian_eig, lcurve_block
from mmflow.threads import n_threads, single_threaded_blas


def tikhonov(gram, rhs, eps):
    """``(G + eps I)^-1 r`` through ``cho_factor``; returns ``(a, cho)`` for reuse (PSF, CLEAN)."""
    if eps <= 0:
        raise InputError("imaging", "eps", f"eps={eps} must be > 0 for a Cholesky solve",
                         "use a positive eps, or method: moore_penrose")
    a = np.array(gram, order="F")  # LAPACK's layout: factored in place, the one n x n copy made
    a[np.diag_indices(len(a))] += eps
    cho = sla.cho_factor(a, lower=False, overwrite_a=True, check_finite=False)
    return sla.cho_solve(cho, rhs, check_finite=False), cho


def moore_penrose(gram, rhs, sigma_threshold):
    """Minimum-norm least squares keeping singular values ``sigma > sigma_threshold``."""
    s, v = hermitian_eig(gram)
    keep = s > sigma_threshold**2
    coef = np.zeros_like(s)
    coef[keep] = 1.0 / s[keep]
    return v @ (_as_column(coef, rhs) * (v.conj().T @ rhs))


def with_prior(gram, rhs, eps, a_prior):
    """Tikhonov towards a prior: minimises ``||v - B a||^2 + eps ||a - a_prior||^2``."""
    a, _ = tikhonov(gram, rhs - _as_column(gram @ a_prior, rhs), eps)
    return a + _as_column(a_prior, rhs)


def smoothness_weights(ell):
    """Diagonal of ``A^H A`` for the gradient norm: ``l (l + 1)`` for the unknowns' ``l``."""
    ell = np.asarray(ell, dtype=float)
    return ell * (ell + 1)


def floored_penalty(penalty_diag):
    """A diagonal ``A^H A`` floored at 1e-12 of its largest element (or of 1): no zero on the diagonal (l = 0)."""
    d = np.asarray(penalty_diag, float)
    return np.maximum(d, 1e-12 * max(d.max(), 1.0))


def generalized(gram, rhs, eps, penalty_diag):
    """``(G + eps A^H A)^-1 r`` for diagonal ``A^H A`` (:func:`floored_penalty`)."""
    d = floored_penalty(penalty_diag)
    a = gram + eps * np.diag(d).astype(gram.dtype)
    return sla.solve(a, rhs, assume_a="her", check_finite=False)


def count_eigenvalues_above(gram, eps):
    """Number of eigenvalues of the Hermitian ``G`` above ``eps``, from an LDL^H factorisation.

    By Sylvester's law of inertia ``eps I - G = L D L^H`` has as many negative eigenvalues as
    ``D``, i.e. as ``G`` has eigenvalues above ``eps``. ``D`` (LAPACK ``?hetrf``, Bunch-Kaufman)
    has 1x1 and 2x2 blocks; a 2x2 block holds one negative eigenvalue if its determinant is
    negative, else two or none by the sign of its trace. About a Cholesky's cost, versus ~10x
    for ``eigvalsh``; exact except for eigenvalues within rounding of ``eps`` (float64 here).
    """
    g = np.asarray(gram)
    n = len(g)
    if n == 0:
        return 0
    a = np.array(-g, dtype=np.complex128, order="F")
    a[np.diag_indices(n)] += eps
    ldu, ipiv, info = lapack.zhetrf(a, lower=0)
    if info < 0:
        raise ValueError(f"zhetrf: illegal argument {-info}")
    diag = ldu.diagonal().real
    neg, k = 0, n - 1
    while k >= 0:  # upper storage: blocks are found from the bottom up
        if ipiv[k] > 0 or k == 0:
            neg += diag[k] < 0
            k -= 1
        else:
            p, q, b = diag[k - 1], diag[k], abs(ldu[k - 1, k])
            det = p * q - b * b
            neg += 1 if det < 0 else (2 if p + q < 0 else 0)
            k -= 2
    return int(neg)


def singular_fraction_above(gram, eps, eigenvalues=None):
    """Fraction of singular values of B above ``sqrt(eps)`` (eigenvalues of G above eps).

    From ``eigenvalues`` when given, else by an inertia count (:func:`count_eigenvalues_above`).
    """
    if eigenvalues is not None:
        return float(np.mean(np.asarray(eigenvalues) > eps)) if len(eigenvalues) else 0.0
    n = len(gram)
    return count_eigenvalues_above(gram, eps) / n if n else 0.0


def _as_column(x, rhs):
    """``x`` (n,) broadcast against ``rhs`` of shape (n,) or (n, k)."""
    x = np.asarray(x)
    return x if np.ndim(rhs) == 1 else x[:, None]


def solve_block(method, gram, rhs, eps, ell=None, a_prior=None, sigma_threshold=None):
    """Dispatch on the configured method name; ``rhs`` (n,) or (n, k) columns solved at once;
    ``ell`` are the unknowns' l (for smoothness)."""
    if method in ("tikhonov", "min_variance"):
        return tikhonov(gram, rhs, eps)[0]
    if method == "moore_penrose":
        return moore_penrose(gram, rhs, np.sqrt(eps) if sigma_threshold is None else sigma_threshold)
    if method == "prior":
        if a_prior is None:
            raise InputError("imaging", "prior_map", "method 'prior' needs a prior map",
                             "set imaging.prior_map to a HEALPix FITS file")
        return with_prior(gram, rhs, eps, a_prior)
    if method == "smoothness":
        return generalized(gram, rhs, eps, smoothness_weights(ell))
    raise InputError("imaging", "method", f"unknown method '{method}'",
                     "use tikhonov, min_variance, moore_penrose, prior or smoothness")


@dataclass
class MSolution:
    """One m block solved: ``alm`` (n_split, lmax - m + 1), the fraction of singular values of
    B above sqrt(eps), and the L-curve ``(n_eps, 2)`` of the first split (or None)."""

    alm: np.ndarray
    fraction_above: float
    lcurve: Optional[np.ndarray]


def solve_m(gram, rhs, m, lmax, method="tikhonov", eps=0.01, filters=None, a_prior=None, vhv=None,
            lcurve_eps=None):
    """Solve one m block for every data split: the one per-m loop of the engine and the workflow.

    The m-filters (:func:`mmflow.imaging.filters.filter_mask`, paper section 4) remove their
    coefficients from the unknowns before solving; the solution is zero there.

    Parameters
    ----------
    gram : (n, n) full Hermitian ``G_m = B^H N^-1 B``, ``n = lmax - m + 1``
    rhs : (n_split, n) ``r_m = B^H N^-1 v`` per data split
    a_prior : (n,) prior coefficients of block m (method ``prior``)
    vhv : ``v^H N^-1 v`` of the first split, and ``lcurve_eps`` trial values: the L-curve
    """
    filters = {} if filters is None else filters
    rhs = np.atleast_2d(rhs)
    keep = filter_mask(m, lmax, **filters)
    want_lc = lcurve_eps is not None
    eig = hermitian_eig(gram) if want_lc and keep.all() else None  # one decomposition serves both
    frac = singular_fraction_above(gram, eps, None if eig is None else eig[0])
    alm = np.zeros(rhs.shape, np.complex128)
    lc = np.zeros((len(lcurve_eps), 2)) if want_lc else None
    if keep.any():
        g, r = (gram, rhs) if keep.all() else (gram[np.ix_(keep, keep)], rhs[:, keep])
        prior = None if a_prior is None else np.asarray(a_prior)[keep]
        alm[:, keep] = solve_block(method, g, r.T, eps, ell=np.arange(m, lmax + 1)[keep], a_prior=prior).T
        if want_lc:
            lc[:, 0], lc[:, 1] = lcurve_block(g, r[0], vhv, lcurve_eps, eig)
    return MSolution(alm, frac, lc)


def solve_alm(acc, eps, method="tikhonov", filters=None, lmax=None, a_prior=None, split=0, ms=None):
    """Solve every m block and assemble a healpy-layout alm vector (Jy/sr, frame of date).

    ``filters``: keyword arguments of :func:`mmflow.imaging.filters.filter_mask`; None applies
    the paper's defaults. Each m goes through :func:`solve_m`, the same
    code as the workflow's ``solve`` stage. ``split`` picks the data split (0: full); ``ms``
    restricts the solve to some m (default all of ``acc.ms``). Blocks are solved concurrently
    on :func:`mmflow.threads.n_threads` threads, one BLAS thread each (the same bits for any
    thread budget).
    """
    lmax = acc.lmax if lmax is None else lmax
    alm = np.zeros(n_alm(lmax), np.complex128)
    ms = acc.ms if ms is None else ms

    def one(m):
        prior = None if a_prior is None else a_prior[m_slice(lmax, m)]
        # full_gram is complex128 (hermitian_full), as in the workflow's solve
        return solve_m(acc.full_gram(m), acc.rhs[m].astype(np.complex128), m, lmax,
                       method, eps, filters, prior)

    # largest blocks first so that the pool stays balanced
    order = sorted(ms)
    with single_threaded_blas(), ThreadPoolExecutor(max_workers=n_threads()) as pool:
        for m, sol in zip(order, pool.map(one, order)):
            alm[m_slice(lmax, m)] = sol.alm[split]
    return alm
