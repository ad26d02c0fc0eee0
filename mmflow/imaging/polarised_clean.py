"""CLEAN of Stokes V in a full-Stokes solve (issue 22): the circularly polarised sky is sparse (pulsars,
flare stars, Jupiter, the Sun), so point components describe it.

The m-mode CLEAN of :mod:`mmflow.imaging.clean` with the full-Stokes operator in place of the Stokes-I
one. With ``H_m = (G_m + D)^-1 G_m`` the map of a true sky ``x = [T; E; B; V]`` through the solve
(:class:`mmflow.imaging.polarised.PolarisedObserver`, factorised once), a major cycle

1. synthesises the residual V map and picks its peaks (:func:`mmflow.imaging.clean.select_components`:
   at most ``n_peaks``, ``min_sep`` apart, above the threshold and ``peak_frac`` of the largest),
2. sets components ``c_i = gain v_i / P_V(dec_i)`` with ``P_V(dec)`` the V map of a unit V point
   source at its own position (:func:`v_psf_table`),
3. subtracts ``H [0; 0; 0; sum_i c_i conj(Y_lm(r_i))]`` from the residual of **all four** Stokes
   parameters: a V component's leakage into I, Q and U through the solve leaves with it.

It stops as :func:`mmflow.imaging.clean.stop_reason` says; the threshold is ``k_sigma`` x the V map's
noise: its jackknife sigma from the data splits where given (the stokes stage's, as the Stokes-I
CLEAN's), else its
robust rms, ``1.4826 MAD`` over the sky the array sees (:func:`robust_rms`: V is noise almost
everywhere), unless a threshold is given. Restoring is :func:`mmflow.imaging.clean.restore_map` with the V
PSF's fitted Gaussian per declination.

The I -> V leakage the regularised solve leaves (the stokes stage's leakage map; ~0.2 % of I at
eps 1e-4 in the tests) is V in the dirty map and CLEANed as such.
"""
from __future__ import annotations

import dataclasses

import healpy
import numpy as np

from mmflow.conventions import n_alm
from mmflow.imaging import psf as psf_mod
from mmflow.imaging.clean import (CleanOptions, CleanState, component_alm, never_seen_dec_min, observed_mask,
                                  select_components)
from mmflow.imaging.maps import default_nside
from mmflow.imaging.polarised import PolarisedObserver
from mmflow.sky.harmonics import point_sources_alm

V = 3  # the row of V in (T, E, B, V)


def v_psf_table(normal, eps, dec_rad, filters=None, observe=None):
    """The V PSF by declination: the V map of a unit V point source at RA 0 and each ``dec_rad``
    through the solve (:class:`mmflow.imaging.polarised.PolarisedObserver`), its peak and fitted Gaussian
    (:func:`mmflow.imaging.psf.fit_psf_columns`: ``dec``, ``peak``, ``major``, ``minor``, ``pa``); ``observe``
    a :class:`mmflow.imaging.polarised.PolarisedObserver` of the same solve, to share its factors."""
    lmax = normal.lmax
    vecs = psf_mod.table_vectors(dec_rad)
    x = np.zeros((len(vecs), 4, n_alm(lmax)), np.complex128)
    for k, vec in enumerate(vecs):
        x[k, V] = point_sources_alm(vec[None], np.ones(1), lmax)
    observe = observe or PolarisedObserver(normal, eps, filters)
    cols = observe(x)[:, V].T  # (n_alm, n_dec)
    return psf_mod.fit_psf_columns(cols, lmax, dec_rad)


def robust_rms(values):
    """``1.4826 median(|x - median(x)|)``: the rms of Gaussian noise, blind to a sparse sky's sources."""
    x = np.asarray(values, float)
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def clean_stokes_v(normal, eps, alm, lat_rad, opts=None, nside=None, filters=None, threshold=None, table=None,
                   dec_step_deg=2.0, observe=None, noise=None):
    """CLEAN the V part of a full-Stokes solve (module docstring).

    Parameters
    ----------
    normal : :class:`mmflow.imaging.polarised.PolarisedNormal`; eps, filters as for the solve
    alm : complex ndarray (4, n_alm), the solve's ``(T, E, B, V)`` (frame of date, Jy/sr)
    lat_rad : float, the array's latitude (the sky it sees: declinations above ``lat - 90 deg``)
    opts : :class:`mmflow.imaging.clean.CleanOptions`
    nside : int, resolution of the residual V maps (default twice :func:`mmflow.imaging.maps.default_nside`)
    threshold : float, optional, Jy/sr; default ``opts.k_sigma`` x ``noise``
    noise : float, optional, the V map's noise sigma, Jy/sr (e.g. its jackknife sigma); default
        :func:`robust_rms` of the dirty V map over the sky seen
    table : dict, optional, the V PSF table (default :func:`v_psf_table` from the lowest seen
        declination to the pole in ``dec_step_deg`` steps)
    observe : :class:`mmflow.imaging.polarised.PolarisedObserver` of the same solve, optional (shares
        its factors); V is signed, so peaks are always ranked by ``|V|`` (``opts.absolute`` is ignored)

    Returns
    -------
    dict: ``state`` (:class:`mmflow.imaging.clean.CleanState` of the V residual and components),
    ``residual`` (4, n_alm) after the subtractions, ``reason``, ``threshold``, ``noise`` (the one given,
    else the robust rms), ``table``.
    """
    opts = dataclasses.replace(opts or CleanOptions(), absolute=True)  # V is signed: both signs are sources
    lmax = normal.lmax
    nside = nside or 2 * default_nside(lmax)
    dec_min = never_seen_dec_min(lat_rad)
    mask = observed_mask(nside, dec_min)
    observe = observe or PolarisedObserver(normal, eps, filters)
    if table is None:
        table = v_psf_table(normal, eps, np.deg2rad(np.arange(np.rad2deg(dec_min), 90.0 + 1e-9, dec_step_deg)),
                            filters, observe)
    residual = np.array(alm, np.complex128, copy=True)
    noise = robust_rms(healpy.alm2map(residual[V], nside, lmax=lmax)[mask]) if noise is None else float(noise)
    thr = opts.k_sigma * noise if threshold is None else float(threshold)
    state = CleanState(residual[V].copy())
    reason = opts.stop(state.peaks, thr)
    while reason is None:
        vmap = healpy.alm2map(residual[V], nside, lmax=lmax)
        vecs, flux, peak = select_components(vmap, table, mask, opts.n_peaks, np.deg2rad(opts.min_sep_deg),
                                             opts.gain, thr, opts.absolute, opts.peak_frac)
        if len(flux):
            x = np.zeros((4, n_alm(lmax)), np.complex128)
            x[V] = component_alm(vecs, flux, lmax)
            residual -= observe(x)[0]
        state = state.advance(residual[V].copy(), vecs, flux, peak)
        reason = opts.stop(state.peaks, thr)
    return {"state": state, "residual": residual, "reason": reason, "threshold": thr, "noise": noise,
            "table": table}
