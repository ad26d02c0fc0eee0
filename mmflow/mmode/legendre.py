"""Orthonormal associated Legendre functions ``lambda_lm(theta)`` with ``Y_lm = lambda_lm e^{i m phi}``.

Condon-Shortley phase included (healpy / scipy convention). Recurrence:

``lambda_mm = (-1)^m sqrt((2m+1)/(4 pi) prod_{k<=m} (2k-1)/(2k)) sin^m theta``,
``lambda_{m+1,m} = sqrt(2m+3) cos theta lambda_mm``,
``lambda_lm = a_lm (cos theta lambda_{l-1,m} - b_lm lambda_{l-2,m})`` with
``a_lm = sqrt((4l^2-1)/(l^2-m^2))``, ``b_lm = sqrt(((l-1)^2-m^2)/(4(l-1)^2-1))``.

The starting value is formed in logarithms so that ``sin^m theta`` does not underflow
before the recurrence climbs out of the evanescent region (safe to lmax ~ 1900 in float64).
"""
import numpy as np
from scipy.special import gammaln


def legendre_table(m, lmax, theta):
    """``lambda_lm(theta_k)`` for ``l = m..lmax``; shape ``(lmax - m + 1, len(theta))``, float64."""
    theta = np.asarray(theta, float)
    x, s = np.cos(theta), np.sin(theta)
    out = np.zeros((lmax - m + 1, len(theta)))
    # log of (2m)! / (4^m (m!)^2) = prod (2k-1)/(2k)
    log_prod = gammaln(2 * m + 1) - 2 * gammaln(m + 1) - m * np.log(4.0)
    with np.errstate(divide="ignore"):
        log_start = 0.5 * (np.log((2 * m + 1) / (4 * np.pi)) + log_prod) + m * np.log(s)
    out[0] = (-1) ** m * np.exp(log_start)
    if lmax > m:
        out[1] = np.sqrt(2 * m + 3) * x * out[0]
    for i, ell in enumerate(range(m + 2, lmax + 1), start=2):
        a = np.sqrt((4.0 * ell * ell - 1) / (ell * ell - m * m))
        b = np.sqrt(((ell - 1.0) ** 2 - m * m) / (4.0 * (ell - 1) ** 2 - 1))
        out[i] = a * (x * out[i - 1] - b * out[i - 2])
    return out
