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

import numpy as np
import scipy.linalg as sla

from mmflow.errors import InputError


def tikhonov(gram, rhs, eps):
    """``(G + eps I)^-1 r`` through ``cho_factor``; returns ``(a, cho)`` for reuse (PSF, CLEAN)."""
    if eps <= 0:
        raise InputError("imaging", "eps", f"eps={eps} must be > 0 for a Cholesky solve",
                         "use a positive eps, or method: moore_penrose")
    a = gram + eps * np.eye(len(gram), dtype=gram.dtype)
    cho = sla.cho_factor(a, lower=False, check_finite=False)
    return sla.cho_solve(cho, rhs, check_finite=False), cho


def moore_penrose(gram, rhs, sigma_threshold):
    """Minimum-norm least squares keeping singular values ``sigma > sigma_threshold``."""
    s, v = np.linalg.eigh(gram)
    keep = s > sigma_threshold**2
    coef = np.zeros_like(s)
    coef[keep] = 1.0 / s[keep]
    return v @ (coef * (v.conj().T @ rhs))


def with_prior(gram, rhs, eps, a_prior):
    """Tikhonov towards a prior: minimises ``||v - B a||^2 + eps ||a - a_prior||^2``."""
    a, _ = tikhonov(gram, rhs - gram @ a_prior, eps)
    return a + a_prior


def smoothness_weights(ell):
    """Diagonal of ``A^H A`` for the gradient norm: ``l (l + 1)`` for the unknowns' ``l``."""
    ell = np.asarray(ell, dtype=float)
    return ell * (ell + 1)


def generalized(gram, rhs, eps, penalty_diag):
    """``(G + eps A^H A)^-1 r`` for diagonal ``A^H A`` (floored at 1e-12 relative for l = 0)."""
    d = np.asarray(penalty_diag, float)
    d = np.maximum(d, 1e-12 * max(d.max(), 1.0))
    a = gram + eps * np.diag(d).astype(gram.dtype)
    return sla.solve(a, rhs, assume_a="her", check_finite=False)


def singular_fraction_above(gram, eps, eigenvalues=None):
    """Fraction of singular values of B above ``sqrt(eps)`` (eigenvalues of G above eps)."""
    s = np.linalg.eigvalsh(gram) if eigenvalues is None else eigenvalues
    return float(np.mean(s > eps)) if len(s) else 0.0


def solve_block(method, gram, rhs, eps, ell=None, a_prior=None, sigma_threshold=None):
    """Dispatch on the configured method name; ``ell`` are the unknowns' l (for smoothness)."""
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
