"""Noise variance of each baseline's m-modes (the ``N`` of ``G = B^H N^-1 B``).

Two estimators:

* :func:`radiometer_variance`: ``sigma^2 = <V_ii> <V_jj> / (dnu tau)`` per sample from the
  time-averaged autocorrelations (the radiometer equation).
* :func:`difference_variance`: ``sigma^2 ~ median |V_t+1 - V_t|^2 / (2 ln 2)`` from successive
  integrations (robust; biased high where the sky moves between integrations).

:func:`mmode_inverse_variance` turns per-sample variances and bin weights into the inverse
variance of the m-modes, ``Var(V_m) = (1/N^2) sum_n sigma^2 / w_n``.
"""
from __future__ import annotations

import numpy as np

from mmflow.errors import InputError
from mmflow.mmode.transform import mmode_noise_variance


def difference_variance(vis, weights):
    """Per-sample variance per baseline from successive differences; ``vis``, ``weights`` ``(time, bl)``.

    ``sigma^2 ~ median(|V_t+1 - V_t|^2) / (2 ln 2)`` over pairs where both samples are
    unflagged (the median of an exponential distribution is ``ln 2`` times its mean).
    """
    d = np.abs(np.diff(vis, axis=0)) ** 2
    ok = (weights[1:] > 0) & (weights[:-1] > 0)
    d = np.where(ok, d, np.nan)
    with np.errstate(all="ignore"):
        med = np.nanmedian(d, axis=0)
    return np.where(np.isfinite(med), med / (2 * np.log(2)), np.inf)


def radiometer_variance(mean_autos, pairs, bandwidth_hz, integration_s, source="visibilities"):
    """``sigma^2_ij = <V_ii> <V_jj> / (dnu tau)`` per baseline and frequency, shape ``(freq, bl)``.

    ``mean_autos``: ``{antenna index: (freq,) time-averaged |V_ii|}``.
    """
    if not mean_autos:
        raise InputError(source, "pairs", "no autocorrelations for the radiometer equation",
                         "set mmode.noise=data, or ingest autocorrelations")
    nf = len(next(iter(mean_autos.values())))
    power = np.full((int(max(pairs.max(), max(mean_autos))) + 1, nf), np.nan)
    for a, v in mean_autos.items():
        power[a] = v
    return (power[pairs[:, 0]] * power[pairs[:, 1]]).T / (bandwidth_hz * integration_s)


def mmode_inverse_variance(sigma2, bin_weight):
    """``1 / Var(V_m)`` per baseline from per-sample ``sigma2`` (bl,) and bin weights (bins, bl); 0 = unusable."""
    sigma2 = np.where(np.isfinite(sigma2), sigma2, np.inf)
    var_m = mmode_noise_variance(bin_weight, 1.0) * np.where(np.isfinite(sigma2), sigma2, 0)
    return np.where((var_m > 0) & np.isfinite(sigma2), 1.0 / np.where(var_m > 0, var_m, 1), 0.0)


def autocorrelation_rows(vis, weights, pairs, n_ant):
    """``|V_ii|`` per integration, antenna and frequency, ``(time, n_ant, freq)`` float32;
    NaN where an antenna's autocorrelation is absent or flagged."""
    out = np.full((vis.shape[0], n_ant, vis.shape[2]), np.nan, np.float32)
    cols = np.flatnonzero(pairs[:, 0] == pairs[:, 1])
    a = np.abs(vis[:, cols, :])
    out[:, pairs[cols, 0], :] = np.where(weights[:, cols, :] > 0, a, np.nan)
    return out
