"""The ``stokes`` stage: full-Stokes imaging (``imaging.stokes: [I, Q, U, V]``), one task per frequency.

Each task reads the m-modes of the four correlations (``mmodes.zarr``'s ``mmodes_corr``, xx, yy,
xy, yx), builds the full-Stokes transfer coefficients of every baseline through the E-field beam
(:func:`mmflow.mmode.polarised_transfer.polarised_pass`, the beam from ``beam``: type
``short_dipole`` or a pyuvdata E-field beam), accumulates ``G_m = B_m^H W B_m`` and
``r_m = B_m^H W v_m`` over the ``4 (lmax - m + 1)`` unknowns ``[T; E; B; V]``
(:func:`mmflow.imaging.polarised.accumulate_polarised_normal`, ``W`` the correlations' relative
inverse noise variances where ``transfer.noise_weighting``) and solves
``x_m = (G_m + D)^-1 r_m`` with ``D = diag(eps, eps_pol, eps_pol, eps_pol)`` and the Stokes-I
solve's m-filters (:func:`mmflow.imaging.polarised.solve_polarised`). It also writes the
leakage: the image through the same solve of the unpolarised sky ``[T, 0, 0, 0]``
(:func:`mmflow.imaging.polarised.expected_alm`), whose Q, U, V are what the beam model leaves of I
in them. With ``clean.enabled`` it CLEANs V (a sparse sky) with the ``clean`` settings
(:func:`mmflow.imaging.polarised_clean.clean_stokes_v`: components from the V residual, subtracted
through the full-Stokes solve from all four Stokes parameters; threshold ``clean.threshold`` or
``clean.threshold_sigma`` x the V map's jackknife noise, or its robust rms without even/odd or
per-day splits). Every data split (``mmode.splits``) is solved through the same factorisation, so
the products can state each Stokes map's jackknife noise. Writes ``stokes.zarr``; the products
stage makes the maps.

The transfer coefficients are the reference kernels (six spherical-harmonic transforms per
baseline and correlation, the whole Gram of a channel in memory: ``16 sum_m (4 L_m)^2`` bytes):
arrays of tens of antennas and lmax of a few tens to ~100 (docs/stokes.md); ``mmflow plan``
states the memory.
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import is_full_stokes, padded_alm
from mmflow.imaging.polarised import (PolarisedObserver, accumulate_polarised_normal, polarisation_response,
                                      stokes_eps)
from mmflow.imaging import psf
from mmflow.imaging.clean import never_seen_dec_min, observed_mask
from mmflow.imaging.polarised_clean import clean_stokes_v, v_psf_table
from mmflow.io.run_stores import STORES, CLEAN_STOPS, stokes_store
from mmflow.mmode.noise import relative_weights
from mmflow.mmode.polarised import CORRELATIONS, make_polarised_grid
from mmflow.mmode.transfer import baselines_in_wavelengths, fringe_bandlimit
from mmflow.sky import units
from mmflow.telescope.beam_factory import make_jones
from mmflow.workflow.engine.clean_state import (
    clean_nside,
    clean_options,
    jackknife_sigma,
    jackknife_splits,
    psf_decs_deg,
)
from mmflow.workflow.engine.kernel_args import m_filters
from mmflow.workflow.stages.stokes.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey

STOKES_CONFIG = (
    "mmode.lmax",
    "mmode.splits",
    "beam",
    "imaging",
    "transfer.noise_weighting",
    "transfer.per_baseline_lmax",
    "clean",
)


def _v_decs(ctx):
    """The V PSF table's declinations (as the Stokes-I CLEAN's: :func:`psf_decs_deg`)."""
    return psf_decs_deg(float(ctx.vis_attrs()["lat_deg"]), ctx.cfg.clean.psf_dec_step_deg)


def _response_decs(lat_rad):
    """Declinations of :func:`~mmflow.imaging.polarised.polarisation_response`'s test sources: the latitude
    and 20, 40 deg either side of it (transits at >= 50 deg elevation), at most 85 deg from the equator."""
    decs = np.rad2deg(lat_rad) + np.array([-40.0, -20.0, 0.0, 20.0, 40.0])
    return np.deg2rad(np.unique(np.clip(decs, -85.0, 85.0)))


def _prepare(ctx):
    mg = ctx.open(STORES.mmodes)
    n_split, nf, n_m = mg[STORES.mmodes.mmodes_corr].shape[:3]
    c = ctx.cfg.clean
    v_clean = (len(_v_decs(ctx)), c.max_cycles, c.peaks_per_cycle) if c.enabled else None
    ctx.create(stokes_store(n_split, nf, ctx.cfg.mmode.lmax, n_m - 1, v_clean))
    return [TaskKey(freq=fi) for fi in range(nf)]


def _task(ctx, key):
    cfg = ctx.cfg
    fi, lmax = key.freq, cfg.mmode.lmax
    vg = ctx.open(STORES.vis)
    freq = float(vg[STORES.vis.freqs_hz][fi])
    pairs = vg[STORES.vis.pairs][:]
    mm = ctx.read(STORES.mmodes.mmodes_corr, (slice(None), slice(fi, fi + 1)))[:, 0]  # (split, m, pm, corr, bl)
    inv_var = ctx.read(STORES.mmodes.inv_var_corr, (slice(fi, fi + 1),))[0]  # (corr, bl)
    w = relative_weights(inv_var) if cfg.transfer.noise_weighting else (inv_var > 0).astype(float)
    keep = np.flatnonzero(w.max(axis=0) > 0)  # baselines with data in some correlation
    jones = make_jones(cfg.beam.model_dump())
    tel = ctx.telescope()
    b = baselines_in_wavelengths(tel, pairs[keep], freq)
    grid = make_polarised_grid(tel.lat_rad, jones, freq, lmax,
                               fringe_bandlimit(np.linalg.norm(b, axis=1), jones.lmax_hint))
    # every data split through one factorisation: split 0 is the full data, the others its jackknives
    lmax_b = tel.baseline_lmax(freq, lmax, pairs[keep]) if cfg.transfer.per_baseline_lmax else None
    normal = accumulate_polarised_normal(grid, b, mm[:, :lmax + 1, :, :, keep], w[:, keep], CORRELATIONS,
                                         lmax_b=lmax_b)
    eps, filters = stokes_eps(cfg.imaging.eps, cfg.imaging.eps_pol), m_filters(cfg.imaging)
    observe = PolarisedObserver(normal, eps, filters)  # factorised once: the solve, the leakage, the CLEAN of V
    splits = observe.solution()  # (split, 4, n_alm)
    alm = splits[0]
    unpolarised = np.zeros_like(alm)
    unpolarised[0] = alm[0]
    leak = observe(unpolarised)[0]
    out = ctx.open(STORES.stokes, mode="r+")
    n_m = out[STORES.stokes.alm].shape[3]
    ctx.write(out, STORES.stokes.alm, (slice(None), slice(fi, fi + 1)),
              np.stack([padded_alm(a, lmax, n_m) for a in splits])[:, None])
    ctx.write(out, STORES.stokes.leakage, (slice(fi, fi + 1),), padded_alm(leak, lmax, n_m)[None])
    info = {"baselines": int(len(keep)), "eps": list(eps),
            "polarisation": polarisation_response(observe, _response_decs(tel.lat_rad), clean_nside(cfg))}
    if cfg.clean.enabled:
        info["v_clean"] = _clean_v(ctx, out, fi, freq, normal, eps, filters, splits, tel.lat_rad, observe)
    return info


def _clean_v(ctx, out, fi, freq, normal, eps, filters, splits, lat_rad, observe):
    """The CLEAN of V (:func:`mmflow.imaging.polarised_clean.clean_stokes_v`) of the full data ``splits[0]``
    with the ``clean`` settings: ``clean.threshold`` if set, else ``clean.threshold_sigma`` x the V map's
    noise: its jackknife sigma where ``mmode.splits`` make one (as the Stokes-I CLEAN), else the dirty V
    map's robust rms."""
    cfg = ctx.cfg
    c, lmax, n_m = cfg.clean, cfg.mmode.lmax, out[STORES.stokes.alm].shape[3]
    thr = None if c.threshold is None else float(units.convert(c.threshold, c.threshold_unit, "Jy/sr", freq))
    jk, names, nside = jackknife_splits(ctx, fi), list(cfg.mmode.splits), clean_nside(cfg)
    # V's jackknife sigma over the sky CLEAN sees, by the Stokes-I CLEAN's estimator (V is spin 0)
    noise = None if jk[0] is None else jackknife_sigma({s: splits[names.index(s)][3] for s in jk[1]}, jk, lmax,
                                                       nside, observed_mask(nside, never_seen_dec_min(lat_rad)))
    table = v_psf_table(normal, eps, np.deg2rad(_v_decs(ctx)), filters, observe)
    res = clean_stokes_v(normal, eps, splits[0], lat_rad, clean_options(c), nside, filters, thr, table,
                         observe=observe, noise=noise)
    st, one = res["state"], (slice(fi, fi + 1),)
    ctx.write(out, STORES.stokes.v_residual, one, padded_alm(res["residual"], lmax, n_m)[None])
    ctx.write(out, STORES.stokes.v_psf_table, one, psf.table_to_array(table)[None], allow_nan=True)
    for cyc in range(st.cycle):  # one chunk per cycle run (flux 0: no component)
        sel = st.comp_cycle == cyc
        comps = np.zeros((1, 1, c.peaks_per_cycle, 4))
        comps[0, 0, :sel.sum()] = np.c_[st.comp_vec[sel], st.comp_flux[sel]]
        ctx.write(out, STORES.stokes.v_components, (slice(fi, fi + 1), slice(cyc, cyc + 1)), comps)
    peaks = np.full(out[STORES.stokes.v_peaks].shape[1], np.nan)
    peaks[:st.cycle] = st.peaks
    ctx.write(out, STORES.stokes.v_peaks, one, peaks[None], allow_nan=True)
    s = STORES.stokes
    for name, value in ((s.v_threshold, res["threshold"]), (s.v_noise, res["noise"]), (s.v_n_cycles, st.cycle),
                        (s.v_stop, CLEAN_STOPS.index(res["reason"]))):
        ctx.write(out, name, one, np.array([value]))
    return {"cycles": int(st.cycle), "components": int(len(st.comp_flux)), "stop": res["reason"],
            "threshold_jy_sr": float(res["threshold"])}


STAGE = Stage(
    "stokes",
    STOKES_CONFIG,
    (STORES.vis, STORES.mmodes),
    (STORES.stokes,),
    _prepare,
    _task,
    enabled=lambda cfg: is_full_stokes(cfg.imaging.stokes),
    description="full-Stokes transfer coefficients (E-field beam), normal equations over T, E, B, V and "
    "Tikhonov per Stokes, per frequency; leakage of the unpolarised sky; CLEAN of V (clean.enabled)",
    cost=COST,
)
