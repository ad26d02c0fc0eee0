"""Noise variance of each baseline's m-modes (the ``N`` of ``G = B^H N^-1 B``).

Per-sample variance ``sigma^2`` (per unit sample weight: ``Var(V_n) = sigma^2 / w_n``), three estimators:

* :func:`radiometer_variance`: ``sigma^2 = <V_ii> <V_jj> / (dnu tau)`` per sample from the
  time-averaged autocorrelations (the radiometer equation). Use it wherever autocorrelations
  exist: it does not depend on the sky's motion, so noiseless data weight all baselines alike.
* :func:`residual_variance`: ``sigma^2 = sum_n w_n |V_n - model_n|^2 / (N_filled - (2 M_b + 1))``
  from the residual of the band-limited least-squares fit
  (:func:`mmflow.mmode.gapfill.lsq_mmodes`): the sky signal is removed first, so long baselines
  are not penalised for their fringe motion. For data without autocorrelations.
* :func:`difference_variance`: ``sigma^2 ~ median |V_t+1 - V_t|^2 / (2 ln 2)`` from successive
  integrations (robust to outliers; biased high by ``|dV/dt|^2`` where the sky moves between
  integrations, i.e. on long baselines: kept for comparison only).

m-mode variances:

* zero-filled transform, :func:`mmode_inverse_variance`: ``Var(V_m) = (1/N^2) sum_n sigma^2 / w_n``
  (the variance of a biased estimate: it falls as bins are flagged, see issue 8 item 5);
* least-squares m-modes, :func:`lsq_mmode_variance`: ``Var(V_m) = sigma^2 / sum_n w_n``, which
  grows as coverage shrinks; :func:`baseline_coverage` then drops or down-weights baselines
  below ``min_coverage``.
"""
from __future__ import annotations

from dataclasses import dataclass

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


def radiometer_variance(mean_autos, pairs, bandwidth_hz, integration_s, source="visibilities", mean_autos_j=None):
    """``sigma^2_ij = <V_ii> <V_jj> / (dnu tau)`` per baseline and frequency, shape ``(freq, bl)``.

    ``mean_autos``: ``{antenna index: (freq,) time-averaged |V_ii|}`` of the feed that antenna i
    correlates; ``mean_autos_j`` those of antenna j's feed where it differs (a cross hand:
    ``sigma^2_ij,xy = <V_ii,xx> <V_jj,yy> / (dnu tau)``).
    """
    if not mean_autos:
        raise InputError(source, "pairs", "no autocorrelations for the radiometer equation",
                         "set mmode.noise=data, or ingest autocorrelations")

    def powers(autos):
        nf = len(next(iter(autos.values())))
        out = np.full((int(max(pairs.max(), max(autos))) + 1, nf), np.nan)
        for a, v in autos.items():
            out[a] = v
        return out

    p_i = powers(mean_autos)
    p_j = p_i if mean_autos_j is None else powers(mean_autos_j)
    return (p_i[pairs[:, 0]] * p_j[pairs[:, 1]]).T / (bandwidth_hz * integration_s)


def mmode_inverse_variance(sigma2, bin_weight):
    """``1 / Var(V_m)`` per baseline from per-sample ``sigma2`` (bl,) and bin weights (bins, bl); 0 = unusable."""
    sigma2 = np.where(np.isfinite(sigma2), sigma2, np.inf)
    var_m = mmode_noise_variance(bin_weight, 1.0) * np.where(np.isfinite(sigma2), sigma2, 0)
    return np.where((var_m > 0) & np.isfinite(sigma2), 1.0 / np.where(var_m > 0, var_m, 1), 0.0)


def autocorrelation_rows(vis, weights, pairs, n_ant):
    """``|V_ii|`` per integration, antenna, frequency (and any trailing axes, e.g. polarisation):
    ``(time, n_ant, freq, ...)`` float32 from ``(time, bl, freq, ...)``; NaN where an antenna's
    autocorrelation is absent or flagged."""
    out = np.full((vis.shape[0], n_ant) + vis.shape[2:], np.nan, np.float32)
    cols = np.flatnonzero(pairs[:, 0] == pairs[:, 1])
    a = np.abs(vis[:, cols, :])
    out[:, pairs[cols, 0], :] = np.where(weights[:, cols, :] > 0, a, np.nan)
    return out


def residual_variance(rss, n_filled, band_limit, signal_power=None, floor_fraction=1e-6):
    """Per-sample ``sigma^2`` per baseline from the residual of the band-limited m-mode fit.

    ``sigma^2 = rss / (N_filled - (2 M_b + 1))`` with ``rss = sum_n w_n |V_n - model_n|^2``: for
    ``Var(V_n) = sigma^2 / w_n`` and a linear fit of ``2 M_b + 1`` complex parameters the
    expected weighted residual is ``sigma^2 (N_filled - (2 M_b + 1))`` (unregularised fit).

    Parameters
    ----------
    rss, n_filled, band_limit : ndarray (n_bl,)
        From :class:`mmflow.mmode.gapfill.LsqMmodes`.
    signal_power : float or ndarray (n_bl,), optional
        ``sum_n w_n |V_n|^2 / N_filled`` (``LsqMmodes.signal_power``). With it ``sigma^2`` is
        floored at ``floor_fraction * max(signal_power)``: one floor for all baselines given
        (a chunk), so noiseless data (simulations without autocorrelations) get finite and
        equal weights, as the radiometer equation would give them, instead of infinite ones
        (or weights set by rounding). Real data sit far above the floor.
    floor_fraction : float

    Returns
    -------
    ndarray (n_bl,): ``inf`` where ``N_filled <= 2 M_b + 1`` (no degrees of freedom left: unusable).
    """
    dof = np.asarray(n_filled, float) - (2 * np.asarray(band_limit, float) + 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s2 = np.where(dof > 0, np.asarray(rss, float) / np.where(dof > 0, dof, 1), np.inf)
    if signal_power is not None:
        floor = floor_fraction * float(np.max(signal_power, initial=0.0))
        s2 = np.where(np.isfinite(s2), np.maximum(s2, floor), s2)
    return s2


def lsq_mmode_variance(sigma2, weight_sum):
    """Variance of least-squares m-modes, ``Var(V_m) = sigma^2 / sum_n w_n`` per baseline.

    Exact (for every m) when the normal matrix is ``c_0 I`` (full coverage, equal weights;
    then it equals ``(1/N^2) sum_n sigma^2 / w_n``), and the mean over m to first order for
    randomly flagged bins. For long gaps it is a lower bound (``tr A^-1 / K >= K / tr A``):
    directions the data leave undetermined are set by the regularisation, not measured.
    ``inf`` where a baseline has no data.
    """
    sigma2 = np.asarray(sigma2, float)
    ws = np.asarray(weight_sum, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ws > 0, sigma2 / np.where(ws > 0, ws, 1), np.inf)


@dataclass
class Coverage:
    """Per-baseline coverage decision of :func:`baseline_coverage`.

    Attributes
    ----------
    fraction : ndarray (n_bl,)
        Fraction of sidereal bins holding data.
    factor : ndarray (n_bl,)
        Multiplier in ``[0, 1]`` for each baseline's inverse variance.
    below : ndarray (n_bl,) bool
        Baselines under ``min_coverage``.
    n_dropped, n_downweighted : int
        Baselines with some data under ``min_coverage``, dropped or down-weighted.
    n_empty : int
        Baselines without any unflagged sample (a flagged antenna, or autocorrelations given
        weight 0 by calibration): factor 0, not counted as low coverage.
    """

    fraction: np.ndarray
    factor: np.ndarray
    below: np.ndarray
    n_dropped: int
    n_downweighted: int
    n_empty: int = 0


COVERAGE_POLICIES = ("drop", "downweight")


def baseline_coverage(bin_weight, min_coverage, policy="drop"):
    """Coverage per baseline and what to do with those below ``min_coverage``.

    ``fraction_b = #{n: w_nb > 0} / N``. Baselines at or above ``min_coverage`` keep factor 1.
    Below it: ``drop`` gives factor 0; ``downweight`` gives ``fraction_b / min_coverage`` (< 1),
    on top of :func:`lsq_mmode_variance`, which already grows like ``1 / fraction_b``: a
    baseline's inverse variance never rises as its coverage falls.
    """
    if policy not in COVERAGE_POLICIES:
        raise InputError("m-mode coverage", "mmode.coverage_policy", f"unknown policy '{policy}'",
                         f"use one of {COVERAGE_POLICIES}")
    if not 0 <= min_coverage <= 1:
        raise InputError("m-mode coverage", "mmode.min_coverage", f"{min_coverage} is not a fraction",
                         "use a value in [0, 1]")
    w = np.asarray(bin_weight)
    frac = np.mean(w > 0, axis=0)
    below = frac < min_coverage
    if policy == "drop":
        factor = np.where(below, 0.0, 1.0)
    else:
        factor = np.where(below, frac / min_coverage if min_coverage > 0 else 1.0, 1.0)
    empty = frac == 0
    factor = np.where(empty, 0.0, factor)
    n_below = int((below & ~empty).sum())
    return Coverage(frac, factor, below, n_below if policy == "drop" else 0,
                    n_below if policy == "downweight" else 0, int(empty.sum()))


def lsq_inverse_variance(sigma2, weight_sum, coverage=None):
    """``1 / Var(V_m)`` of least-squares m-modes per baseline times the coverage factor; 0 = unusable."""
    var = lsq_mmode_variance(sigma2, weight_sum)
    factor = 1.0 if coverage is None else coverage.factor
    ok = np.isfinite(var) & (var > 0)
    return np.where(ok, factor / np.where(ok, var, 1), 0.0)


def relative_weights(inv_var):
    """Noise weights scaled to unit mean over the measured baselines.

    ``w_b = N_b^-1 / <N^-1>_{b: N_b^-1 > 0}``: minimum-variance weighting changes the relative
    weights of baselines, not the scale of ``B^H N^-1 B``, so eps keeps the meaning it has for
    unweighted data (the paper's eps = 0.01).

    Parameters
    ----------
    inv_var : array_like
        Inverse noise variances, any shape; 0 marks a baseline without data.

    Returns
    -------
    numpy.ndarray
        ``inv_var`` (as float) divided by the mean of its positive entries; returned unscaled
        when no entry is positive.
    """
    inv_var = np.asarray(inv_var, float)
    good = inv_var > 0
    return inv_var / inv_var[good].mean() if good.any() else inv_var
