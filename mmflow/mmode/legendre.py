"""Orthonormal associated Legendre functions ``lambda_lm(theta)`` with ``Y_lm = lambda_lm e^{i m phi}``.

Condon-Shortley phase included (healpy / scipy convention). Recurrence:

``lambda_mm = (-1)^m sqrt((2m+1)/(4 pi) prod_{k<=m} (2k-1)/(2k)) sin^m theta``,
``lambda_{m+1,m} = sqrt(2m+3) cos theta lambda_mm``,
``lambda_lm = a_lm (cos theta lambda_{l-1,m} - b_lm lambda_{l-2,m})`` with
``a_lm = sqrt((4l^2-1)/(l^2-m^2))``, ``b_lm = sqrt(((l-1)^2-m^2)/(4(l-1)^2-1))``.

Range. ``lambda_mm ~ sin^m theta`` is far below float64's smallest number near the poles
(about ``exp(-lmax/e)`` at the turning point ``sin theta = m / lmax``, i.e. 1e-160 at lmax 1000
and 1e-320 -- subnormal -- at lmax 2000), yet the recurrence climbs out of that evanescent
region to O(1) values before ``l = lmax``. So the recurrence carries, per ring, a scaled value
and an integer exponent: ``lambda = p * 2^(256 s)``. The start ``lambda_mm`` is formed in
logarithms (``gammaln``) and split into ``p in (2^-256, 1]`` and ``s <= 0``; whenever
``|p| > 2^256`` while ``s < 0`` both recurrence values are multiplied by ``2^-256`` and ``s``
grows by one. Values are written as ``p * 2^(256 s)`` (exactly 0 where that is below
float64's range, i.e. below 1e-308 -- negligible). Nothing can overflow or underflow to a
wrong value at any lmax; tested to lmax 2000 (``tests/unit/test_numerics.py``: orthonormality by
Gauss-Legendre quadrature, agreement with ducc0's independent recursion, closed forms at the
poles and the equator; ``docs/numerics.md``).
"""
from functools import lru_cache

import numba
import numpy as np
from scipy.special import gammaln

_SHIFT = 256  # rescaling step: a factor 2^256 per exponent unit
_LOG_STEP = _SHIFT * np.log(2.0)


def legendre_table(m, lmax, theta):
    """``lambda_lm(theta_k)`` for ``l = m..lmax``; shape ``(lmax - m + 1, len(theta))``, float64."""
    out, _ = weighted_legendre_table(m, lmax, theta)
    return out


def weighted_legendre_table(m, lmax, theta, weights=None, dtype=np.float64, l_block=256):
    """``w_k lambda_lm(theta_k)`` for ``l = m..lmax`` in ``dtype``, and its column maxima per l-block.

    The product is formed in float64 and rounded once to ``dtype`` as it is written (one pass
    over memory: no float64 table, weighting or reduction passes afterwards).

    Returns
    -------
    table : (lmax - m + 1, n) ``dtype``
    colmax : (n_blocks, n) float64, ``max_{l in block} |w_k lambda_lm(theta_k)|`` for l-blocks
        of ``l_block`` rows starting at ``l = m``.
    """
    theta = np.ascontiguousarray(theta, float).ravel()
    x, s = np.cos(theta), np.sin(theta)
    # log |lambda_mm| = 0.5 log((2m+1)/(4 pi) (2m)! / (4^m (m!)^2)) + m log sin theta
    log_prod = gammaln(2 * m + 1) - 2 * gammaln(m + 1) - m * np.log(4.0)
    with np.errstate(divide="ignore"):
        log_sin = m * np.log(np.abs(s)) if m > 0 else np.zeros_like(s)  # 0 * log 0 would be NaN
        log_start = 0.5 * (np.log((2 * m + 1) / (4 * np.pi)) + log_prod) + log_sin
    exponent = np.minimum(np.ceil(log_start / _LOG_STEP), 0.0)
    exponent[~np.isfinite(exponent)] = 0.0  # sin theta = 0, m > 0: lambda_lm = 0 for every l
    start = (-1.0) ** m * np.exp(log_start - exponent * _LOG_STEP)  # exp(-inf) = 0 at the poles
    w = np.ones(len(theta)) if weights is None else np.ascontiguousarray(weights, float)
    out = np.empty((lmax - m + 1, len(theta)), dtype)
    colmax = np.zeros(((lmax - m) // l_block + 1, len(theta)))
    _kernel()(m, lmax, x, start, exponent.astype(np.int64), w, out, colmax, l_block)
    return out, colmax


@lru_cache(maxsize=1)
def _kernel():
    """Compile the scaled recurrence (numba) on first use."""
    big = 2.0 ** _SHIFT
    small = 2.0 ** -_SHIFT
    # 2^(256 s) for s = 0, -1, -2, -3, -4 (2^-1024 is subnormal); 0 below
    powers = np.array([2.0 ** (-_SHIFT * j) for j in range(5)])

    @numba.njit(nogil=True, boundscheck=False, cache=True)
    def scaled_recurrence(m, lmax, x, start, exponent, w, out, colmax, l_block):
        n = x.shape[0]
        prev = np.zeros(n)
        cur = start.copy()
        e = exponent.copy()
        for ell in range(m, lmax + 1):
            i = ell - m
            if ell == m + 1:
                c1 = np.sqrt(2.0 * m + 3.0)
                for k in range(n):
                    prev[k] = cur[k]
                    cur[k] = c1 * x[k] * cur[k]
            elif ell > m + 1:
                a = np.sqrt((4.0 * ell * ell - 1.0) / (ell * ell - m * m))
                b = np.sqrt(((ell - 1.0) ** 2 - m * m) / (4.0 * (ell - 1.0) ** 2 - 1.0))
                for k in range(n):
                    nxt = a * (x[k] * cur[k] - b * prev[k])
                    prev[k] = cur[k]
                    cur[k] = nxt
                    if e[k] < 0 and abs(nxt) > big:
                        cur[k] *= small
                        prev[k] *= small
                        e[k] += 1
            blk = i // l_block
            for k in range(n):
                v = w[k] * (cur[k] * powers[-e[k]] if -e[k] < 5 else 0.0)
                out[i, k] = v
                colmax[blk, k] = max(colmax[blk, k], abs(v))

    return scaled_recurrence
