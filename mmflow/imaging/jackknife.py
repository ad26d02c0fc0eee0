"""Jackknife noise of a map from even and odd integrations (paper section 4, Table 1).

Split the sidereal grid ``phi_n = 2 pi n / N`` into its even (``n = 2k``) and odd
(``n = 2k + 1``) bins. Each half is an ``N/2``-bin grid; the odd half sits half a bin of the
new grid away from ``2 pi k / (N/2)``, so its m-modes carry the phase
``exp(-i m 2 pi / N)``: they are transformed at their true angles
(``phi = 2 pi (2k + p) / N + offset``, :func:`mmflow.mmode.transform.split_bins`), never as if they sat on the
half grid. With the true angles every half measures the same sky m-modes (for
``m < N/2 - mmax_sky``), and ``V_m(all) = (V_m(even) + V_m(odd)) / 2`` exactly.

Imaging each half with the same operator (same Gram, eps and filters) as the full data keeps
``map_all = (map_even + map_odd) / 2``, and the jackknife estimate of the full map's noise
variance is

``sigma^2 = (1/2) mean_observed(|odd - all|^2 + |even - all|^2)``,

unbiased for independent noise in the two halves: ``odd - all = (odd - even) / 2``.

With data of several sidereal days, the ``day<k>`` splits (:mod:`mmflow.mmode.splits`) give a
per-day jackknife (:func:`per_day_variance`), which also sees errors slower than one
integration (but faster than a day); the ``day`` / ``night`` splits give a map of day-night
systematics (:func:`day_night_difference`), not a noise estimate. The shares ``f_k`` of both
count the unflagged samples of each split (:func:`mmflow.mmode.splits.split_shares`).
"""
from __future__ import annotations

import numpy as np

from mmflow.errors import InputError
from mmflow.imaging.psf import gaussian_solid_angle, interp_table
from mmflow.mmode.splits import day_splits
from mmflow.mmode.transform import split_mmode_transform
from mmflow.sky import units


def split_mmodes(binned, mmax, offset=None):
    """``{"all", "even", "odd"}`` m-modes of one sidereal grid (the data-split axis).

    The ``full``, ``even`` and ``odd`` splits of :func:`mmflow.mmode.transform.split_mmode_transform`:
    the even / odd bins ``n = 2k + p`` transformed at their true angles
    ``phi = 2 pi (2k + p) / N + offset_n``.

    Parameters
    ----------
    binned : ndarray (N, ...)
        Sidereally binned data on ``phi_n = 2 pi n / N (+ offset_n)``; N even, ``N / 2 >= 2 mmax + 1``.
    offset : ndarray (N,), optional
        Per-bin offsets from :func:`mmflow.mmode.transform.sidereal_bins`.

    Returns
    -------
    dict of ndarray (mmax + 1, 2, ...), as :func:`mmflow.mmode.transform.mmode_transform`.
    """
    n = binned.shape[0]
    if n % 2 or n // 2 < 2 * mmax + 1:
        raise InputError("jackknife", "n_bins", f"{n} sidereal bins cannot be halved for mmax={mmax}",
                         f"use an even number of bins >= {2 * (2 * mmax + 1)}")
    return dict(zip(("all", "even", "odd"), split_mmode_transform(binned, mmax, offset, ("full", "even", "odd"))))


def jackknife_variance(map_all, map_even, map_odd, mask=None):
    """``(1/2) mean(|odd - all|^2 + |even - all|^2)`` over the pixels in ``mask``."""
    sel = slice(None) if mask is None else np.asarray(mask, bool)
    d_odd = np.asarray(map_odd)[sel] - np.asarray(map_all)[sel]
    d_even = np.asarray(map_even)[sel] - np.asarray(map_all)[sel]
    return float(0.5 * np.mean(np.abs(d_odd) ** 2 + np.abs(d_even) ** 2))


def per_day_variance(map_all, day_maps, fractions, mask=None):
    """Per-day jackknife estimate of the full map's noise variance, over the pixels in ``mask``:

    ``sigma_all^2 = mean_k [ f_k / (1 - f_k) ] |day_k - all|^2``,

    which for ``D`` equal days (``f_k = 1/D``) is ``sigma_all^2 = mean_k |day_k - all|^2 / (D - 1)``.

    Derivation: day ``k`` holds the share ``f_k`` of the data's weight (its integrations over
    all), its map noise ``n_k`` has variance ``sigma_all^2 / f_k`` (inverse-variance weights
    add), and the full map is the weighted mean ``all = sum_j f_j day_j`` (the same linear
    operator images every split). Then ``day_k - all = (1 - f_k) n_k - sum_{j != k} f_j n_j``
    has variance ``(1 - f_k)^2 sigma_all^2 / f_k + sum_{j != k} f_j sigma_all^2
    = sigma_all^2 (1 - f_k) / f_k``, so each listed day gives an unbiased
    ``f_k / (1 - f_k) |day_k - all|^2``; the mean over the listed days (any subset of the data's
    days) is the estimate. For ``D = 2`` equal days it is
    ``(1/2)(|day_0 - all|^2 + |day_1 - all|^2)``, the even/odd formula of :func:`jackknife_variance`.
    Unequal days (a flagged stretch) enter through ``f_k``, the day's share of the unflagged
    samples (:func:`mmflow.mmode.splits.split_shares`; a day below min_coverage is refused by
    the stage); this assumes each day's weight is
    spread over the sidereal bins like the full data's (a day with a long gap is noisier at
    the LSTs it misses, which one ``f_k`` cannot say).

    Parameters
    ----------
    map_all : ndarray
        The full data's map.
    day_maps : sequence of ndarray
        The maps of the ``day<k>`` splits (all days of the data or some of them).
    fractions : sequence of float
        ``f_k``, each day's share of the data's unflagged samples (``0 < f_k < 1``).
    """
    sel = slice(None) if mask is None else np.asarray(mask, bool)
    f = np.asarray(fractions, float)
    if len(day_maps) == 0 or len(f) != len(day_maps) or np.any((f <= 0) | (f >= 1)):
        raise InputError("jackknife", "fractions", f"{len(day_maps)} day maps with shares {f.tolist()}",
                         "give one share 0 < f_k < 1 per day map (two or more days in the data)")
    full = np.asarray(map_all)[sel]
    terms = [fk / (1 - fk) * np.mean(np.abs(np.asarray(m)[sel] - full) ** 2) for m, fk in zip(day_maps, f)]
    return float(np.mean(terms))


def day_night_difference(map_day, map_night, f_day, f_night):
    """The day/night systematics map ``sqrt(f_d f_n) (day - night)``.

    ``f_d``, ``f_n``: the day and night halves' shares of the data (:func:`mmflow.mmode.splits.split_shares`,
    ``f_d + f_n = 1``). A systematics check, not a noise estimate: the two halves differ by the
    thermal noise *and* by everything that depends on the time of day (the Sun and its
    sidelobes, the day-time ionosphere, RFI and the system temperature's daily cycle). Each
    half's noise has variance ``sigma_all^2 / f`` (inverse-variance weights add), so noise alone
    gives ``Var = f_d f_n (sigma_all^2 / f_d + sigma_all^2 / f_n) = (f_d + f_n) sigma_all^2 =
    sigma_all^2``, the full map's noise, for any shares (``(day - night) / 2`` for equal halves;
    that plain half-difference would give ``sigma_all^2 / (4 f_d f_n)``, 1.19 sigma_all^2 for
    0.3 / 0.7). An rms well above the jackknife sigma measures day-night systematics. Only
    meaningful for data spanning months, where each half covers every LST.
    """
    f_d, f_n = float(f_day), float(f_night)
    if not (0 < f_d < 1 and 0 < f_n < 1):
        raise InputError("jackknife", "fractions", f"day / night shares {f_d:g} / {f_n:g}",
                         "give shares 0 < f < 1 (both halves must hold data)")
    return np.sqrt(f_d * f_n) * (np.asarray(map_day) - np.asarray(map_night))


def masked_rms(hmap, mask=None):
    """``sqrt(mean |x|^2)`` over the pixels in ``mask``."""
    sel = slice(None) if mask is None else np.asarray(mask, bool)
    return float(np.sqrt(np.mean(np.abs(np.asarray(hmap)[sel]) ** 2)))


def split_variance(maps, kind, fractions=None, mask=None):
    """The full map's jackknife noise variance from the split maps ``{name: map}``.

    ``kind``: ``"even_odd"`` (:func:`jackknife_variance` of ``full``, ``even``, ``odd``) or
    ``"per_day"`` (:func:`per_day_variance` over every ``day<k>`` map, ``fractions[name]`` its ``f_k``).
    """
    if kind == "even_odd":
        return jackknife_variance(maps["full"], maps["even"], maps["odd"], mask)
    if kind == "per_day":
        days = sorted(day_splits(maps).items())
        return per_day_variance(maps["full"], [maps[s] for _, s in days], [fractions[s] for _, s in days], mask)
    raise ValueError(f"unknown jackknife '{kind}'")


def noise_realisation(maps, kind, fractions=None):
    """One realisation of the full map's noise from the splits (alm or maps, linear):
    ``(odd - even) / 2`` (even/odd), else ``sqrt(f_k / (1 - f_k)) (day_k - all)`` of the first
    listed day (per-day): each has the variance the jackknife estimates."""
    if kind == "even_odd":
        return 0.5 * (np.asarray(maps["odd"]) - np.asarray(maps["even"]))
    if kind != "per_day":
        raise ValueError(f"unknown jackknife '{kind}'")
    name = day_splits(maps)[min(day_splits(maps))]
    f = float(fractions[name])
    return np.sqrt(f / (1 - f)) * (np.asarray(maps[name]) - np.asarray(maps["full"]))


def noise_summary(sigma_jy_sr, freq_hz, beam_solid_angle_sr):
    """The noise in the units of Table 1: K and mJy/beam (``sigma Omega_beam``)."""
    return {"jy_per_sr": float(sigma_jy_sr),
            "kelvin": float(units.jy_per_sr_to_kelvin(sigma_jy_sr, freq_hz)),
            "mjy_per_beam": float(1e3 * sigma_jy_sr * beam_solid_angle_sr)}


def jackknife_noise(map_all, map_even, map_odd, mask, freq_hz, psf_table, beam_dec_deg=45.0):
    """Table 1's noise: jackknife sigma (Jy/sr, K, mJy/beam), the beam being the fitted PSF
    main lobe at ``beam_dec_deg`` (``Omega = pi / (4 ln 2) major minor``)."""
    return beam_noise(np.sqrt(jackknife_variance(map_all, map_even, map_odd, mask)), freq_hz, psf_table,
                      beam_dec_deg)


def beam_noise(sigma, freq_hz, psf_table, beam_dec_deg=45.0):
    """:func:`noise_summary` of ``sigma`` (Jy/sr) with the fitted PSF main lobe at ``beam_dec_deg`` as
    the beam, and that beam's solid angle."""
    dec = np.deg2rad(beam_dec_deg)
    omega = gaussian_solid_angle(interp_table(psf_table, dec, "major"), interp_table(psf_table, dec, "minor"))
    return {**noise_summary(sigma, freq_hz, omega), "beam_solid_angle_sr": float(omega)}
