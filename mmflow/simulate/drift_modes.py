"""A band-limited sky's drift scan from a few sidereal angles: exact trigonometric interpolation.

As the Earth turns by ``phi`` the sky turns about the pole, and a sky of band limit ``L``,
``I = sum_{l <= L} a_lm Y_lm``, turned by ``phi`` is ``sum a_lm e^{i m phi} Y_lm`` (paper eq. 3):
every baseline's visibility is a trigonometric polynomial of degree ``L`` in the sidereal angle,

    V(phi) = sum_{|m| <= L} v_m e^{i m phi},

whatever the beam and the baseline (the m-modes ``v_m``, paper eq. 4). Its values at
``N >= 2 L + 1`` equally spaced angles determine it, and a DFT of them gives the ``v_m``
(:func:`coefficients_from_samples`); it is then evaluated at any sidereal angle (:func:`evaluate_drift`).
The simulator's direct sum over the sky's quadrature grid is so done ``N`` times instead of once per
integration: for the paper's day (6,628 integrations) and ``L = 64``, 130 sums instead of 6,628.
The samples come from :func:`mmflow.simulate.visibilities.simulate_drift_scan`, the same
measurement equation the point sources go through, so this shares nothing with the transfer
matrices either.
"""
from __future__ import annotations

import numpy as np

#: samples beyond 2 L + 1: the quadrature's own error is not exactly band-limited, and a margin keeps
#: what lies just above L from folding onto the modes kept
MARGIN = 8


def n_samples(lmax):
    """Sidereal angles sampled for a sky of band limit ``lmax``: ``2 lmax + 1 + MARGIN``, made even."""
    n = 2 * int(lmax) + 1 + MARGIN
    return n + n % 2


def sample_lsts(lmax):
    """The sampled sidereal angles ``2 pi k / N`` (rad), ``k = 0 .. N - 1``."""
    n = n_samples(lmax)
    return 2 * np.pi * np.arange(n) / n


def coefficients_from_samples(samples):
    """``v_m`` (N, ...) from visibilities at :func:`sample_lsts` (N, ...), in numpy's FFT order
    (``m = np.fft.fftfreq(N, 1 / N)``): ``v_m = (1 / N) sum_k V(phi_k) e^{-i m phi_k}``."""
    samples = np.asarray(samples)
    return np.fft.fft(samples, axis=0) / samples.shape[0]


def evaluate_drift(coeffs, lsts, lmax):
    """``V(phi) = sum_{|m| <= lmax} v_m e^{i m phi}`` at the sidereal angles ``lsts`` (T,) -> (T, ...).

    The modes above ``lmax`` (the sky has none; the samples' margin holds the quadrature's residue)
    are dropped. One complex GEMM: (T, 2 lmax + 1) x (2 lmax + 1, n_bl)."""
    coeffs = np.asarray(coeffs)
    n = coeffs.shape[0]
    m = np.rint(np.fft.fftfreq(n, 1.0 / n)).astype(int)
    keep = np.abs(m) <= lmax
    phase = np.exp(1j * np.outer(np.asarray(lsts, float), m[keep]))
    flat = coeffs[keep].reshape(int(keep.sum()), -1)
    return (phase @ flat).reshape((len(lsts),) + coeffs.shape[1:])
