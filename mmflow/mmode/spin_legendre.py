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


def weighted_spin_tables(m, lmax, theta, weights=None, dtype=np.float64, flush=False, lmax_spin=None):
    """``w_k lambda_lm`` for ``l = m..lmax`` and ``w_k W_lm``, ``w_k X_lm`` for ``l = m..lmax_spin`` (default
    lmax) at rings ``theta_k``, rows in parity order: the ``(lmax - m) // 2 + 1`` rows of even ``l - m``
    first, then the odd ones (``W``, ``X`` likewise over their own rows; none where ``m > lmax_spin``: the
    transfer's E and B stop at ``imaging.stokes_lmax``, :func:`mmflow.mmode.polarised_transfer.polarised_block`).

    ``flush``: each row's entries below ``eps^2`` of the row's largest (``|t_k| < eps^2 max_k |t_k|``,
    compared in ``dtype``, ``eps`` its machine epsilon) are zeroed as the row is written (a GEMM over
    the row then moves by less than ``eps`` of the rounding of its largest term and never takes the
    CPU's subnormal path: :func:`mmflow.mmode.polarised_transfer.polarised_tables`). Every row is formed
    alone from ``lambda_lm`` and ``lambda_{l-1,m}``: a row's bits do not depend on ``lmax`` or ``lmax_spin``.

    Returns
    -------
    lam : ``dtype`` ``(lmax - m + 1, n)``; w_tab, x_tab : ``dtype`` ``(max(0, lmax_spin - m + 1), n)``; in each,
        ``t[:ne]`` and ``t[ne:]`` are the even and odd rows (contiguous, ``ne`` the table's own), formed in
        float64 and rounded once as they are written.
    """
    theta = np.ascontiguousarray(theta, float).ravel()
    lam = legendre_table(m, lmax, theta)
    w = np.ones(len(theta)) if weights is None else np.ascontiguousarray(weights, float)
    n_spin = max(0, min(lmax, lmax if lmax_spin is None else int(lmax_spin)) - m + 1)
    out = np.empty((lmax - m + 1, len(theta)), dtype)
    spin = np.empty((2, n_spin, len(theta)), dtype)
    tiny = np.finfo(dtype).eps ** 2 if flush else np.zeros((), dtype)[()]
    _kernel()(m, lam, np.cos(theta), 1.0 / np.sin(theta) ** 2, w, out, spin, tiny)
    return out, spin[0], spin[1]


def spin2_tables(m, lmax, theta):
    """``(W_lm(theta_k), X_lm(theta_k))`` for ``l = m..lmax`` in l order: float64 ``(lmax - m + 1, n)``."""
    _, w_tab, x_tab = weighted_spin_tables(m, lmax, theta)
    order = np.argsort(np.r_[np.arange(0, lmax - m + 1, 2), np.arange(1, lmax - m + 1, 2)], kind="stable")
    return w_tab[order], x_tab[order]


@lru_cache(maxsize=1)
def _kernel():
    """Compile the one-pass table kernel (numba) on first use."""

    @numba.njit(nogil=True, boundscheck=False, cache=True)
    def tables(m, lam, c, inv_s2, w, out, spin, tiny):
        n_l, n = lam.shape
        n_s = spin.shape[1]
        ne, ne_s = (n_l - 1) // 2 + 1, (n_s - 1) // 2 + 1
        for i in range(n_l):
            ell = m + i
            row = i // 2 if i % 2 == 0 else ne + i // 2
            big0 = tiny - tiny  # the row's largest |entry|, in out's dtype
            for k in range(n):
                out[row, k] = w[k] * lam[i, k]
                big0 = max(big0, abs(out[row, k]))
            if tiny > 0:  # the row's negligible entries zeroed, compared in out's dtype
                cut = tiny * big0
                for k in range(n):
                    v = out[row, k]
                    out[row, k] = v if abs(v) >= cut else 0.0
            if i >= n_s:
                continue
            row = i // 2 if i % 2 == 0 else ne_s + i // 2
            norm = 2.0 / np.sqrt((ell - 1.0) * ell * (ell + 1.0) * (ell + 2.0)) if ell >= 2 else 0.0
            c_lm = np.sqrt((2.0 * ell + 1.0) / (2.0 * ell - 1.0) * (ell * ell - m * m)) if ell > m else 0.0
            a = ell - m * m
            h = ell * (ell - 1.0) / 2.0
            big1 = big2 = tiny - tiny
            for k in range(n):
                cur = lam[i, k]
                prev = lam[i - 1, k] if i > 0 else 0.0
                g_plus = -(a * inv_s2[k] + h) * cur + c_lm * c[k] * inv_s2[k] * prev
                g_minus = m * inv_s2[k] * (c_lm * prev - (ell - 1.0) * c[k] * cur)
                spin[0, row, k] = w[k] * norm * g_plus
                spin[1, row, k] = w[k] * norm * g_minus
                big1 = max(big1, abs(spin[0, row, k]))
                big2 = max(big2, abs(spin[1, row, k]))
            if tiny > 0:
                for j in range(2):
                    cut = tiny * (big1 if j == 0 else big2)
                    for k in range(n):
                        v = spin[j, row, k]
                        spin[j, row, k] = v if abs(v) >= cut else 0.0

    return tables
