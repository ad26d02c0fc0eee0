"""Spin-2 Legendre functions ``W_lm``, ``X_lm`` from the orthonormal ``lambda_lm`` (healpy convention).

The spin-weighted harmonics are ``sY_lm(theta, phi) = s_lambda_lm(theta) e^{i m phi}``; for spin
``+-2`` (Zaldarriaga & Seljak 1997; Gorski et al. 2005, eq. for the polarised HEALPix
transforms)::

    W_lm = (2_lambda_lm + -2_lambda_lm) / 2 = 2 N_l G+_lm,     X_lm = (2_lambda_lm - -2_lambda_lm) / 2 = 2 N_l G-_lm,
    G+_lm = -((l - m^2) / sin^2 theta + l (l - 1) / 2) lambda_lm + c_lm cos theta / sin^2 theta lambda_{l-1,m},
    G-_lm = m / sin^2 theta (c_lm lambda_{l-1,m} - (l - 1) cos theta lambda_lm),
    N_l = ((l - 1) l (l + 1) (l + 2))^(-1/2),     c_lm = ((2l + 1) / (2l - 1) (l^2 - m^2))^(1/2),

zero for ``l < 2`` (``lambda_{l-1,m}`` is the same recurrence one row earlier, zero at ``l = m``).
Symmetries used by the folded transfer (:mod:`mmflow.mmode.polarised_transfer`):
``W_lm(pi - theta) = (-1)^(l+m) W_lm(theta)``, ``X_lm(pi - theta) = -(-1)^(l+m) X_lm(theta)``, and
``W_{l,-m} = (-1)^m W_lm``, ``X_{l,-m} = -(-1)^m X_lm``.

The ``lambda_lm`` come from :func:`mmflow.mmode.legendre.legendre_table` (scaled recurrence, no
underflow at any lmax); the ``1 / sin^2 theta`` terms are finite on Gauss-Legendre rings, which
never touch a pole, but cancel there: the absolute error grows to ~``1e-16 / sin^2 theta`` on the
polar rings (2e-11 of the functions' O(1) peak at lmax 1000, far below float32 transfer blocks).
Tested against ducc0's spin-2 synthesis at lmax 1000 (``tests/unit/mmode/test_polarised_fast.py``).
"""
from __future__ import annotations

from functools import lru_cache

import numba
import numpy as np

from mmflow.mmode.legendre import legendre_table


def weighted_spin_tables(m, lmax, theta, weights=None, dtype=np.float64, flush=False):
    """``w_k lambda_lm``, ``w_k W_lm``, ``w_k X_lm`` at rings ``theta_k`` for ``l = m..lmax``, rows in
    parity order: the ``ne = (lmax - m) // 2 + 1`` rows of even ``l - m`` first, then the odd ones.

    ``flush``: each row's entries below ``eps^2`` of the row's largest (``|t_k| < eps^2 max_k |t_k|``,
    compared in ``dtype``, ``eps`` its machine epsilon) are zeroed as the row is written (a GEMM over
    the row then moves by less than ``eps`` of the rounding of its largest term and never takes the
    CPU's subnormal path: :func:`mmflow.mmode.polarised_transfer.polarised_tables`).

    Returns
    -------
    lam, w_tab, x_tab : ``dtype`` arrays ``(lmax - m + 1, n)``; ``t[:ne]`` and ``t[ne:]`` are the even
        and odd rows (contiguous), formed in float64 and rounded once as they are written.
    """
    theta = np.ascontiguousarray(theta, float).ravel()
    lam = legendre_table(m, lmax, theta)
    w = np.ones(len(theta)) if weights is None else np.ascontiguousarray(weights, float)
    out = np.empty((3, lmax - m + 1, len(theta)), dtype)
    tiny = np.finfo(dtype).eps ** 2 if flush else np.zeros((), dtype)[()]
    _kernel()(m, lam, np.cos(theta), 1.0 / np.sin(theta) ** 2, w, out, tiny)
    return out[0], out[1], out[2]


def spin2_tables(m, lmax, theta):
    """``(W_lm(theta_k), X_lm(theta_k))`` for ``l = m..lmax`` in l order: float64 ``(lmax - m + 1, n)``."""
    _, w_tab, x_tab = weighted_spin_tables(m, lmax, theta)
    order = np.argsort(np.r_[np.arange(0, lmax - m + 1, 2), np.arange(1, lmax - m + 1, 2)], kind="stable")
    return w_tab[order], x_tab[order]


@lru_cache(maxsize=1)
def _kernel():
    """Compile the one-pass table kernel (numba) on first use."""

    @numba.njit(nogil=True, boundscheck=False, cache=True)
    def tables(m, lam, c, inv_s2, w, out, tiny):
        n_l, n = lam.shape
        ne = (n_l - 1) // 2 + 1
        for i in range(n_l):
            ell = m + i
            row = i // 2 if i % 2 == 0 else ne + i // 2
            norm = 2.0 / np.sqrt((ell - 1.0) * ell * (ell + 1.0) * (ell + 2.0)) if ell >= 2 else 0.0
            c_lm = np.sqrt((2.0 * ell + 1.0) / (2.0 * ell - 1.0) * (ell * ell - m * m)) if ell > m else 0.0
            a = ell - m * m
            h = ell * (ell - 1.0) / 2.0
            big0 = big1 = big2 = tiny - tiny  # the row's largest |entry|, in out's dtype
            for k in range(n):
                cur = lam[i, k]
                prev = lam[i - 1, k] if i > 0 else 0.0
                g_plus = -(a * inv_s2[k] + h) * cur + c_lm * c[k] * inv_s2[k] * prev
                g_minus = m * inv_s2[k] * (c_lm * prev - (ell - 1.0) * c[k] * cur)
                out[0, row, k] = w[k] * cur
                out[1, row, k] = w[k] * norm * g_plus
                out[2, row, k] = w[k] * norm * g_minus
                big0 = max(big0, abs(out[0, row, k]))
                big1 = max(big1, abs(out[1, row, k]))
                big2 = max(big2, abs(out[2, row, k]))
            if tiny > 0:  # the row's negligible entries zeroed, compared in out's dtype
                for j, big in ((0, big0), (1, big1), (2, big2)):
                    cut = tiny * big
                    for k in range(n):
                        v = out[j, row, k]
                        out[j, row, k] = v if abs(v) >= cut else 0.0

    return tables
