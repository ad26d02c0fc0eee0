"""Autocorrelation ripple correction: the 0.1 dB HVAC gain sawtooth (paper section 3.2).

Per antenna and polarisation, with ``a(t)`` the autocorrelation amplitude on a regular grid
of integrations and ``w(t)`` its weight (0 = flagged):

1. outliers: ``|a - med_k(a)| > n_mad * 1.4826 * MAD`` (running median over ``k``
   integrations, MAD over the series) are flagged;
2. smoothing: a flag-aware Gaussian-weighted *local linear* fit (FWHM ``smooth_fwhm_s``,
   default 45 min)::

       s(t) = (S2 Y0 - S1 Y1) / (S0 S2 - S1^2),
       S_n = sum_t' K(t'-t) w(t') (t'-t)^n,   Y_n = sum_t' K(t'-t) w(t') (t'-t)^n a(t')

   which is unbiased for a linear trend at edges and next to flagged gaps (a plain
   normalised convolution is biased there by the slope of the sky's slow variation);
3. ratio ``r(t) = a(t) / s(t)``: autos are corrected by ``r_i``, cross-correlations by
   ``sqrt(r_i r_j)``, i.e. gains ``sqrt(r)`` applied with
   :func:`mmflow.calibrate.gain_apply.apply_gains` (on read, never rewriting the data).

The sky's own variation is slow (hours) and survives: its 24 h harmonic is attenuated by the
smoothing by ``1 - exp(-2 pi^2 sigma^2 / P^2) ~ 0.3 %`` of its amplitude for sigma = 19 min.
"""
from __future__ import annotations

import warnings

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.ndimage import correlate1d

from mmflow.calibrate.gain_apply import apply_gains


def autocorrelations(vis, weights, pairs, n_ant):
    """Autocorrelation amplitudes and weights (time, n_ant, pol); antennas without one get w = 0."""
    pairs = np.asarray(pairs)
    T, _, P = np.shape(vis)
    a = np.zeros((T, n_ant, P))
    w = np.zeros((T, n_ant, P))
    auto = np.flatnonzero(pairs[:, 0] == pairs[:, 1])
    a[:, pairs[auto, 0]] = np.abs(np.asarray(vis)[:, auto])
    w[:, pairs[auto, 0]] = np.broadcast_to(weights, np.shape(vis))[:, auto]
    return a, w


def running_median_outliers(a, w, window=11, n_mad=5.0, rel_floor=1e-3, block=64):
    """Flags (same shape as ``a``, time first) of samples ``> n_mad`` robust sigmas from a running median.

    Flagged samples (w = 0) are ignored by the median (NaN-aware) and never flagged again. The
    robust sigma is floored at ``rel_floor`` x the series' median level (an autocorrelation's
    radiometer noise is >= 1 / sqrt(24 kHz x 13 s) ~ 2e-3 of it), so noiseless data are not
    flagged for following the sawtooth.
    """
    T = a.shape[0]
    flat_a = a.reshape(T, -1)
    flat_w = w.reshape(T, -1)
    out = np.zeros(flat_a.shape, bool)
    half = window // 2
    for c0 in range(0, flat_a.shape[1], block):
        x = np.where(flat_w[:, c0:c0 + block] > 0, flat_a[:, c0:c0 + block], np.nan)
        xp = np.pad(x, ((half, window - 1 - half), (0, 0)), constant_values=np.nan)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(sliding_window_view(xp, window, axis=0), axis=-1)
            dev = x - med
            mad = 1.4826 * np.nanmedian(np.abs(dev), axis=0)
            level = np.nanmedian(np.abs(x), axis=0)
        mad = np.maximum(np.nan_to_num(mad), rel_floor * np.nan_to_num(level))
        out[:, c0:c0 + block] = np.abs(dev) > n_mad * np.maximum(mad, 1e-300)
    return out.reshape(a.shape)


def local_linear_smooth(a, w, sigma_samples, truncate=4.0):
    """Flag-aware Gaussian local-linear smoothing along axis 0 (see the module docstring).

    Samples with no weight within the kernel get NaN.
    """
    r = int(np.ceil(truncate * sigma_samples))
    tau = np.arange(-r, r + 1, dtype=float)
    k = np.exp(-0.5 * (tau / sigma_samples) ** 2)
    wa = w * a

    def c(x, kern):
        return correlate1d(x, kern, axis=0, mode="constant", cval=0.0)

    s0, s1, s2 = c(w, k), c(w, k * tau), c(w, k * tau**2)
    y0, y1 = c(wa, k), c(wa, k * tau)
    det = s0 * s2 - s1**2
    ok = det > 1e-12 * np.maximum(s0 * s2, 1e-300)
    with np.errstate(all="ignore"):
        lin = (s2 * y0 - s1 * y1) / det
        const = y0 / s0
    return np.where(ok, lin, np.where(s0 > 0, const, np.nan))


def ripple_ratio(autos, weights, integration_s, smooth_fwhm_s=2700.0, median_window=11, n_mad=5.0):
    """``r(t) = a(t) / s(t)`` per (time, antenna, pol) and the outlier flags.

    Parameters
    ----------
    autos, weights : ndarray (time, n_ant, pol) on a regular integration grid (gaps: w = 0)
    integration_s : float, the grid spacing
    smooth_fwhm_s : float, FWHM of the Gaussian kernel (default 45 min)
    median_window, n_mad : outlier detection (:func:`running_median_outliers`)

    Returns
    -------
    ratio : ndarray (time, n_ant, pol); 1 where there is no data
    outliers : bool ndarray (time, n_ant, pol): samples flagged here (add them to the flags)
    """
    a = np.asarray(autos, float)
    w = np.asarray(weights, float).copy()
    outliers = running_median_outliers(a, w, median_window, n_mad) & (w > 0)
    w[outliers] = 0.0
    sigma = smooth_fwhm_s / np.sqrt(8 * np.log(2)) / integration_s
    s = local_linear_smooth(a, w, sigma)
    with np.errstate(all="ignore"):
        ratio = np.where((w > 0) & (s > 0), a / s, 1.0)
    return ratio, outliers


def apply_ripple(vis, weights, pairs, ratio, feeds=None, out=None):
    """Corrected (vis, weights): autos / r_i, crosses / sqrt(r_i r_j) (``feeds``, ``out``: as in
    :func:`mmflow.calibrate.gain_apply.apply_gains`, for the cross hands; in place)."""
    return apply_gains(vis, weights, pairs, np.sqrt(ratio), feeds=feeds, out=out)
