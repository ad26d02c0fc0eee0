"""CLEAN in a full-Stokes solve: the compact sources' Stokes vectors through the run's own response
(issue 39), and the CLEAN of Stokes V (issue 22).

The m-mode CLEAN of :mod:`mmflow.imaging.clean` with the full-Stokes operator in place of the Stokes-I
one. With ``H_m = (G_m + D)^-1 G_m`` the map of a true sky ``x = [T; E; B; V]`` through the solve
(:class:`mmflow.imaging.polarised.PolarisedObserver`, factorised once) and ``A(dec)`` the 4 x 4 response
matrix of a point source (:func:`mmflow.imaging.polarised.response_matrices`: ``A[X, Y]`` the Stokes-X map at
the source of a unit Stokes-Y source there; tabled by declination, the same at every RA), a major cycle of
:func:`clean_stokes`

1. synthesises the residual map of the Stokes parameter that places components (``select``: I for the
   compact sources, V for the CLEAN of V) and picks its peaks (:func:`mmflow.imaging.clean.select_components`:
   at most ``n_peaks``, ``min_sep`` apart, above the threshold and ``peak_frac`` of the largest),
2. reads the four residual maps at each peak, ``d`` (:func:`mmflow.imaging.polarised.stokes_at`), and sets
   the component's Stokes vector ``s = gain A_F^-1 d_F`` over the fitted parameters ``F`` (``fit``: all four,
   or V alone); where ``cond(A) > COND_MAX`` the array does not measure polarisation there and the
   component is ``s = (gain d_I / A_II, 0, 0, 0)``,
3. subtracts ``H [T; E; B; V](sum_i s_i delta(r - r_i))`` from the residual of **all four** Stokes
   parameters: a component's leakage through the solve leaves with it.

Why all four: the regularised solve shrinks Q, U, V (``eps_pol``: to 0.1-0.3 of the truth on ordinary
arrays at the defaults) and leaks I into them; both are in ``A``, so a point source's fitted Stokes vector is
its own whatever eps and eps_pol are, while the maps (the diffuse sky) stay regularised. :func:`stokes_sources`
groups the components into sources, adds the last residual through ``A^-1`` and states each one's fractions,
angle and ``cond(A)``.

It stops as :func:`mmflow.imaging.clean.stop_reason` says; the threshold is ``k_sigma`` x the selecting
map's noise: its jackknife sigma from the data splits where given (the stokes stage's, as the Stokes-I
CLEAN's), else its robust rms, ``1.4826 MAD`` over the sky the array sees (:func:`robust_rms`), unless a
threshold is given. Restoring is :func:`mmflow.imaging.clean.restore_map` with the PSF's fitted Gaussian per
declination (the table's).
"""
from __future__ import annotations

import dataclasses

import healpy
import numpy as np

from mmflow.conventions import radec_to_vec
from mmflow.imaging import psf as psf_mod
from mmflow.imaging.clean import CleanOptions, CleanState, never_seen_dec_min, observed_mask, select_components
from mmflow.imaging.maps import default_nside
from mmflow.imaging.polarised import (PolarisedObserver, point_source_stokes_alm, response_matrices, stokes_at,
                                      stokes_response)

I, V = 0, 3  # the rows of I and V in (I, Q, U, V) and (T, E, B, V)
#: a component's (a source's) Stokes vector is solved through ``A`` only where ``cond(A)`` (2-norm) is below
#: this: a relative error ``e`` of the maps at the source (the residual, the position's) becomes up to
#: ``cond(A) e`` of I in the fitted fractions, and the CLEAN leaves ``e ~ 1e-4``, so 20 keeps the fractions
#: within ~0.2 % of I (docs/stokes.md); above it the array does not measure polarisation there
COND_MAX = 20.0


#: declinations imaged at once by :func:`psf_table` (4 sources each): the images in memory are 16 x 4 x n_alm
#: (0.5 GB at lmax 1000), each pass one solve (a factorisation of every m where the factors are not kept)
DECS_PER_PASS = 4


def psf_table(observe, dec_rad, beam=I, fit=(I, 1, 2, V)):
    """The response table of :func:`clean_stokes` by declination (RA 0): ``matrix`` ``(n_dec, 4, 4)``
    (:func:`mmflow.imaging.polarised.response_matrices`: the columns of the Stokes parameters ``fit``, the
    others 0) and the PSF of Stokes ``beam`` (one of ``fit``; its map of a unit source of its own: ``dec``,
    ``peak``, ``major``, ``minor``, ``pa``, :func:`mmflow.imaging.psf.fit_psf_columns`; the Gaussian restores
    the components), from :func:`mmflow.imaging.polarised.stokes_response` (``DECS_PER_PASS`` declinations a
    pass)."""
    dec = np.asarray(dec_rad, float).reshape(-1)
    fit = tuple(fit)
    cols, mats = [], []
    for k in range(0, len(dec), DECS_PER_PASS):
        images = stokes_response(observe, dec[k:k + DECS_PER_PASS], fit)
        cols.append(images[:, fit.index(beam), beam])
        mats.append(response_matrices(images, dec[k:k + DECS_PER_PASS], observe.lmax, fit))
    table = psf_mod.fit_psf_columns(np.concatenate(cols).T, observe.lmax, dec)
    table["matrix"] = np.concatenate(mats)
    return table


def v_psf_table(normal, eps, dec_rad, filters=None, observe=None):
    """The V PSF by declination: the V map of a unit V point source at RA 0 and each ``dec_rad``
    through the solve, its peak and fitted Gaussian and ``A_VV`` (:func:`psf_table` of V alone);
    ``observe`` a :class:`mmflow.imaging.polarised.PolarisedObserver` of the same solve, to share its
    factors."""
    return psf_table(observe or PolarisedObserver(normal, eps, filters), dec_rad, beam=V, fit=(V,))


def robust_rms(values):
    """``1.4826 median(|x - median(x)|)``: the rms of Gaussian noise, blind to a sparse sky's sources."""
    x = np.asarray(values, float)
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def matrices_at(table, vecs):
    """``A`` ``(n, 4, 4)`` at unit vectors ``vecs``: the table's matrices interpolated linearly in declination."""
    dec = np.arcsin(np.clip(np.asarray(vecs, float).reshape(-1, 3)[:, 2], -1, 1))
    a = np.asarray(table["matrix"]).reshape(len(table["dec"]), 16)
    return np.stack([np.interp(dec, table["dec"], a[:, k]) for k in range(16)], axis=1).reshape(-1, 4, 4)


def solve_stokes(a, d, fit=(I, 1, 2, V), cond_max=COND_MAX):
    """The Stokes vectors ``s`` ``(n, 4)`` with ``A_F s_F = d_F`` over the fitted parameters ``F`` (the others
    0), and ``cond(A_F)`` ``(n,)``; where the condition number exceeds ``cond_max``, I alone
    (``s_I = d_I / A_II``)."""
    fit = list(fit)
    out, cond = np.zeros((len(d), 4)), np.ones(len(d))
    for k, (ak, dk) in enumerate(zip(a, d)):
        sub = ak[np.ix_(fit, fit)]
        cond[k] = np.linalg.cond(sub) if len(fit) > 1 else 1.0
        if cond[k] <= cond_max:
            out[k, fit] = np.linalg.solve(sub, dk[fit])
        else:
            out[k, I] = dk[I] / ak[I, I]
    return out, cond


def clean_stokes(observe, alm, lat_rad, opts=None, nside=None, threshold=None, noise=None, table=None,
                 dec_step_deg=2.0, select=I, fit=(I, 1, 2, V)):
    """CLEAN of a full-Stokes solve (module docstring): components placed on the peaks of Stokes ``select``,
    their Stokes vectors ``gain A_F^-1 d_F`` over ``fit``.

    Parameters
    ----------
    observe : :class:`mmflow.imaging.polarised.PolarisedObserver` of the solve (its factors are shared)
    alm : complex ndarray (4, n_alm), the solve's ``(T, E, B, V)`` (frame of date, Jy/sr)
    lat_rad : float, the array's latitude (the sky it sees: declinations above ``lat - 90 deg``)
    opts : :class:`mmflow.imaging.clean.CleanOptions` (``absolute`` ranks the peaks by ``|X|``)
    nside : int, resolution of the residual maps (default twice :func:`mmflow.imaging.maps.default_nside`)
    threshold : float, optional, Jy/sr; default ``opts.k_sigma`` x ``noise``
    noise : float, optional, the selecting map's noise sigma, Jy/sr (e.g. its jackknife sigma); default
        :func:`robust_rms` of its dirty map over the sky seen
    table : dict, optional, :func:`psf_table` (default from the lowest seen declination to the pole in
        ``dec_step_deg`` steps, with the PSF of ``select``)
    select : int, the Stokes parameter whose peaks place the components (0 = I, 3 = V)
    fit : the Stokes parameters each component fits (the others stay 0)

    Returns
    -------
    dict: ``vec`` (n, 3), ``stokes`` (n, 4) Jy, ``cycle`` (n,) of the components, ``peaks`` (the selecting
    map's largest residual before each cycle), ``cycles``, ``residual`` (4, n_alm) after the subtractions,
    ``reason``, ``threshold``, ``noise`` (the one given, else the robust rms), ``table``.
    """
    opts = opts or CleanOptions()
    lmax = observe.lmax
    nside = nside or 2 * default_nside(lmax)
    dec_min = never_seen_dec_min(lat_rad)
    mask = observed_mask(nside, dec_min)
    if table is None:
        table = psf_table(observe, np.deg2rad(np.arange(np.rad2deg(dec_min), 90.0 + 1e-9, dec_step_deg)), select, fit)
    residual = np.array(alm, np.complex128, copy=True)
    noise = robust_rms(healpy.alm2map(residual[select], nside, lmax=lmax)[mask]) if noise is None else float(noise)
    thr = opts.k_sigma * noise if threshold is None else float(threshold)
    vec, stokes, cycle, peaks = [np.zeros((0, 3))], [np.zeros((0, 4))], [np.zeros(0, int)], []
    reason = None
    while reason is None:
        rmap = healpy.alm2map(residual[select], nside, lmax=lmax)
        vecs, _, peak = select_components(rmap, table, mask, opts.n_peaks, np.deg2rad(opts.min_sep_deg), opts.gain,
                                          thr, opts.absolute, opts.peak_frac)
        if len(vecs):
            s = opts.gain * solve_stokes(matrices_at(table, vecs), stokes_at(residual, vecs, lmax), fit)[0]
            residual -= observe(point_source_stokes_alm(vecs, s, lmax))[0]
            vec.append(vecs)
            stokes.append(s)
            cycle.append(np.full(len(vecs), len(peaks)))
        peaks.append(peak)
        reason = opts.stop(peaks, thr)
    return {"vec": np.concatenate(vec), "stokes": np.concatenate(stokes), "cycle": np.concatenate(cycle),
            "peaks": np.array(peaks), "cycles": len(peaks), "residual": residual, "reason": reason, "threshold": thr,
            "noise": noise, "table": table}


def stokes_sources(result, lmax, cond_max=COND_MAX, max_sources=None):
    """The sources of a :func:`clean_stokes` of all four Stokes parameters: its components grouped, each
    source's Stokes vector, fractions and angle.

    Components are taken in decreasing ``|I|``; each not yet taken starts a source with every untaken one
    within half the PSF's FWHM (the table's ``major`` at its declination; the CLEAN of a point source puts
    components of both signs on the PSF's sidelobes further out, which the source's sum leaves out). A
    source sits at the ``|I|``-weighted mean direction ``r`` of its components, and its Stokes vector is
    their sum plus the residual at ``r`` through ``A(r)^-1`` (:func:`solve_stokes`: a last step of loop
    gain 1, so the stated vector depends little on how deep the CLEAN went); a source is stated only where
    its own peak, ``I A_II(r)``, is above the CLEAN's threshold (noise and negative sidelobe components left
    out). ``measured``:
    ``cond(A(r)) <= cond_max``; where not, Q, U, V and the fractions are None (the array does not measure
    polarisation there) instead of amplified numbers.

    Returns
    -------
    list of dicts, brightest I first (at most ``max_sources``): ``ra_deg``, ``dec_deg`` (frame of date),
    ``stokes_jy`` ``[I, Q, U, V]``, ``linear_fraction`` ``sqrt(Q^2 + U^2) / I``, ``angle_deg``
    ``0.5 atan2(U, Q)`` (IAU: north through east, in (-90, 90]), ``circular_fraction`` ``V / I``, ``cond``,
    ``measured``, ``components``.
    """
    return _stated(result, list(_source_steps(result, lmax, cond_max)), cond_max, max_sources)


def _stated(result, steps, cond_max, max_sources):
    """The sources' dicts of :func:`stokes_sources` from their :func:`_source_steps`, brightest I first."""
    out = []
    for _, g, r, s, cond in steps:
        s = result["stokes"][g].sum(axis=0) + s
        ok = bool(cond <= cond_max)
        src = {"ra_deg": float(np.rad2deg(np.arctan2(r[1], r[0])) % 360), "dec_deg": float(np.rad2deg(np.arcsin(r[2]))),
               "stokes_jy": [float(s[I])] + ([float(x) for x in s[1:]] if ok else [None] * 3),
               "linear_fraction": float(np.hypot(s[1], s[2]) / s[I]) if ok else None,
               "angle_deg": float(np.rad2deg(0.5 * np.arctan2(s[2], s[1]))) if ok else None,
               "circular_fraction": float(s[V] / s[I]) if ok else None,
               "cond": float(cond), "measured": ok, "components": int(len(g))}
        out.append(src)
    out.sort(key=lambda src: -src["stokes_jy"][I])
    return out[:max_sources]


def _source_steps(result, lmax, cond_max):
    """The sources of :func:`stokes_sources` before their vectors are summed: per source above the threshold
    ``(its brightest component's index, its components' indices, r, the last step A(r)^-1 d(r), cond(A(r)))``."""
    vec, st, table = result["vec"], result["stokes"], result["table"]
    order = np.argsort(-np.abs(st[:, I]), kind="stable")
    fwhm = psf_mod.interp_table(table, np.arcsin(np.clip(vec[:, 2], -1, 1)), "major")
    free = np.ones(len(vec), bool)
    groups = []
    for k in order:
        if free[k]:
            member = free & (vec @ vec[k] >= np.cos(0.5 * fwhm[k] if np.isfinite(fwhm[k]) else 0.0))
            free &= ~member
            groups.append((k, np.flatnonzero(member)))
    for k, g in groups:
        r = (np.abs(st[g, I])[:, None] * vec[g]).sum(axis=0)
        r /= np.linalg.norm(r)
        a = matrices_at(table, r)
        step, cond = solve_stokes(a, stokes_at(result["residual"], r, lmax), cond_max=cond_max)
        if (st[g].sum(axis=0) + step[0])[I] * a[0, I, I] <= result["threshold"]:  # its own peak not above it
            continue
        yield k, g, r, step[0], cond[0]


def close_sources(observe, result, cond_max=COND_MAX, max_sources=None):
    """The sources :func:`stokes_sources` states, each one's last step (``A(r)^-1`` of the residual at its place
    ``r``, loop gain 1) then taken into the CLEAN: added to the source's brightest component, its image
    (``observe``, the solve's :class:`mmflow.imaging.polarised.PolarisedObserver`) subtracted from the residual.
    The residual's Q, U, V at a source are the prior's shrunken part of what the components left (1.5-6.8 % of
    the linear fractions in the workflow test before): restored maps (residual + components) then hold at each
    source the Stokes vector stated, not the shrunken one. ``result`` (:func:`clean_stokes`'s) is updated in
    place; the sources returned are those stated before the step (after it they move by what the step's place
    changes: the brightest component's, within half the PSF's FWHM of ``r``), from one grouping for both."""
    lmax = observe.lmax
    steps = list(_source_steps(result, lmax, cond_max))
    sources = _stated(result, steps, cond_max, max_sources)
    if steps:
        first = np.array([k for k, *_ in steps])
        step = np.array([s for *_, s, _ in steps])
        result["stokes"][first] += step
        result["residual"] -= observe(point_source_stokes_alm(result["vec"][first], step, lmax))[0]
    return sources


def source_vectors(sources):
    """Unit vectors ``(n, 3)`` of :func:`stokes_sources`' sources (frame of date)."""
    return radec_to_vec(np.deg2rad([s["ra_deg"] for s in sources]), np.deg2rad([s["dec_deg"] for s in sources]))


def clean_stokes_v(normal, eps, alm, lat_rad, opts=None, nside=None, filters=None, threshold=None, table=None,
                   dec_step_deg=2.0, observe=None, noise=None):
    """CLEAN the V part of a full-Stokes solve: :func:`clean_stokes` selecting on V's peaks and fitting V alone
    (``c_i = gain v_i / A_VV(dec_i)``), V ranked by ``|V|`` whatever ``opts.absolute`` says (V is signed).

    ``normal``, ``eps``, ``filters`` as for the solve (``observe``, a
    :class:`mmflow.imaging.polarised.PolarisedObserver` of it, shares its factors); ``table``: :func:`v_psf_table`;
    the rest as :func:`clean_stokes`. Returns its dict with ``state``, a
    :class:`mmflow.imaging.clean.CleanState` of the V residual and the components' V.
    """
    opts = dataclasses.replace(opts or CleanOptions(), absolute=True)  # V is signed: both signs are sources
    observe = observe or PolarisedObserver(normal, eps, filters)
    out = clean_stokes(observe, alm, lat_rad, opts, nside, threshold, noise, table, dec_step_deg, select=V, fit=(V,))
    out["state"] = CleanState(out["residual"][V].copy(), out["vec"], out["stokes"][:, V], out["cycle"], out["peaks"],
                              out["cycles"])
    return out
