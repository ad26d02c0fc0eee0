"""The ``stokes`` stage: full-Stokes imaging (``imaging.stokes: [I, Q, U, V]``), in blocks of m.

Phase one, one task per (frequency, block of m): the task reads the block's m-modes of the four
correlations (``mmodes.zarr``'s ``mmodes_corr``, xx, yy, xy, yx), builds the full-Stokes transfer
coefficients of every baseline for those m through the E-field beam
(:func:`mmflow.mmode.polarised_transfer.polarised_pass`, each chunk of baselines on a grid of its own
size; the beam from ``beam``: type ``short_dipole`` or a pyuvdata E-field beam), accumulates
``G_m = B_m^H W B_m`` and ``r_m = B_m^H W v_m`` over the unknowns ``[T; E; B; V]`` (T to ``mmode.lmax``,
E, B, V to ``imaging.stokes_lmax``: :func:`mmflow.imaging.polarised.accumulate_polarised_normal`, ``W``
the correlations' relative inverse noise variances where ``transfer.noise_weighting``), solves
``x_m = (G_m + D)^-1 r_m`` with ``D = diag(eps, eps_pol, eps_pol, eps_pol)`` and the Stokes-I solve's
m-filters for every data split (``mmode.splits``) through one factorisation, images the leakage (the
unpolarised sky ``[T, 0, 0, 0]`` through the same solve, :func:`mmflow.imaging.polarised.expected_alm`),
and writes the block's harmonics, leakage and Grams to ``stokes.zarr``. The blocks
(:func:`mmflow.imaging.polarised.stokes_m_blocks`) keep a task's Grams (in the accumulation's precision; each
m's factor is made and dropped in turn) and m-modes within ``BLOCK_BYTES``: no task holds a channel's whole Gram.

Phase two, one task per frequency: the polarisation response of test sources through the run's solve
(:func:`mmflow.imaging.polarised.polarisation_response`), the full-Stokes CLEAN of the compact sources (always:
:func:`mmflow.imaging.polarised_clean.clean_stokes`, components on the I map's positive peaks, each one's Stokes vector
through the 4 x 4 response at its position, so that the sources' fractions are not the regularised maps'
shrunken ones; the ``clean`` settings, its threshold as the CLEAN of V's with I's noise; the sources, their
fractions, angles and condition numbers go to the task's info, :func:`mmflow.imaging.polarised_clean.stokes_sources`)
and, with ``clean.enabled``, the CLEAN of V (a
sparse sky; :func:`mmflow.imaging.polarised_clean.clean_stokes_v`: components from the V residual,
subtracted through the full-Stokes solve from all four Stokes parameters; threshold ``clean.threshold``
or ``clean.threshold_sigma`` x the V map's jackknife noise, or its robust rms without even/odd or
per-day splits), through the stored Grams factorised one m at a time
(:class:`mmflow.imaging.polarised.PolarisedObserver` with ``keep_factors``, and the Grams read once, only when a
channel's Grams and factors fit ``KEPT_BYTES``; else the largest m's factors within ``FACTORS_KEPT_BYTES`` are
kept, :func:`blocks.factors_kept`). The products stage makes the maps.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from mmflow.conventions import complex_dtype, healpy_alm, is_full_stokes, padded_alm
from mmflow.imaging.polarised import (PolarisedNormal, PolarisedObserver,
                                      accumulate_polarised_normal, polarisation_response, stokes_eps)
from mmflow.imaging import psf
from mmflow.imaging.clean import never_seen_dec_min, observed_mask
from mmflow.imaging.polarised_clean import (COND_MAX, I, V, clean_stokes, clean_stokes_v, close_sources, psf_table,
                                            v_psf_table)
from mmflow.io.run_stores import VIS_METADATA, STORES, CLEAN_STOPS, stokes_store
from mmflow.mmode.noise import relative_weights
from mmflow.mmode.polarised import CORRELATIONS, make_polarised_grid
from mmflow.mmode.engine import GridCache
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
from mmflow.workflow.engine.geometry import stokes_lmax_of
from mmflow.workflow.engine.kernel_args import m_filters
from mmflow.workflow.stages.stokes.blocks import blocks_of, factors_kept, gram_dtype, kept_in_memory, sizes_of
from mmflow.workflow.stages.stokes.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey

STOKES_CONFIG = (
    "mmode.lmax",
    "transfer.dtype",
    "mmode.splits",
    "beam",
    "imaging",
    "transfer.noise_weighting",
    "transfer.per_baseline_lmax",
    "clean",
)


#: the declination step (deg) of the sources' response table at least: ``A(dec)`` is smooth in declination and
#: only paces the CLEAN (each cycle subtracts the components' exact image); 5 deg against
#: ``clean.psf_dec_step_deg`` (2) makes the table 2.5x cheaper (docs/stokes.md)
SOURCES_DEC_STEP_DEG = 5.0


def _source_decs(ctx):
    """The sources' response table's declinations (:func:`psf_decs_deg` at ``SOURCES_DEC_STEP_DEG`` or the
    ``clean.psf_dec_step_deg`` if coarser)."""
    step = max(ctx.cfg.clean.psf_dec_step_deg, SOURCES_DEC_STEP_DEG)
    return psf_decs_deg(float(ctx.vis_attrs()["lat_deg"]), step)


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
    n_bl = mg[STORES.mmodes.mmodes_corr].shape[-1]
    cfg = ctx.cfg
    c = cfg.clean
    sources = (len(_source_decs(ctx)), c.max_cycles, c.peaks_per_cycle)
    v_clean = (len(_v_decs(ctx)), c.max_cycles, c.peaks_per_cycle) if c.enabled else None
    blocks = blocks_of(cfg, n_split, n_bl)
    ctx.create(stokes_store(n_split, nf, cfg.mmode.lmax, n_m - 1, v_clean, blocks, stokes_lmax_of(cfg),
                            gram_dtype(cfg), sources))
    return [TaskKey(freq=fi, m_block=m0) for fi in range(nf) for m0, _ in blocks]


def _split_baselines(ctx):
    """Data splits and baselines of the m-modes (what the blocks of m depend on besides the settings)."""
    shape = ctx.open(STORES.mmodes)[STORES.mmodes.mmodes_corr].shape
    return shape[0], shape[-1]


def _next_cycle(ctx, cycle):
    """Phase two after the blocks: one task per frequency (the response and the CLEAN of V)."""
    if cycle > 0:
        return None
    return [TaskKey(freq=fi) for fi in range(ctx.open(STORES.mmodes)[STORES.mmodes.mmodes_corr].shape[1])]


def _task(ctx, key):
    return _block_task(ctx, key) if key.m_block is not None else _channel_task(ctx, key)


def _block_task(ctx, key):
    """Phase one: the normal equations, solve and leakage of one block of m (module docstring)."""
    cfg = ctx.cfg
    fi, lmax, lmax_p = key.freq, cfg.mmode.lmax, stokes_lmax_of(cfg)
    vg = ctx.open(STORES.vis)
    freq = float(vg[STORES.vis.freqs_hz][fi])
    pairs = vg[STORES.vis.pairs][:]
    n_split, n_bl = _split_baselines(ctx)
    m0 = key.m_block
    m1 = dict(blocks_of(cfg, n_split, n_bl))[m0]
    inv_var = ctx.read(STORES.mmodes.inv_var_corr, (slice(fi, fi + 1),))[0]  # (corr, bl)
    w = relative_weights(inv_var) if cfg.transfer.noise_weighting else (inv_var > 0).astype(float)
    keep = np.flatnonzero(w.max(axis=0) > 0)  # baselines with data in some correlation
    mm = _block_mmodes(ctx, fi, (m0, m1), keep, complex_dtype(cfg.transfer.dtype))
    normal = block_normal(cfg, ctx.telescope(), freq, pairs[keep], mm, w[:, keep], (m0, m1))
    splits, leak = block_solve(cfg, normal)
    out = ctx.open(STORES.stokes, mode="r+")
    n_m = out[STORES.stokes.alm].shape[3]
    mb = slice(m0, min(m1, n_m))
    ctx.write(out, STORES.stokes.alm, (slice(None), slice(fi, fi + 1), slice(None), mb),
              np.stack([padded_alm(a, lmax, n_m)[:, mb] for a in splits])[:, None])
    ctx.write(out, STORES.stokes.leakage, (slice(fi, fi + 1), slice(None), mb),
              padded_alm(leak, lmax, n_m)[None, :, mb])
    name = STORES.stokes.gram(fi, m0)
    n0, gdt = out[name].shape[1], out[name].dtype
    for k, g in enumerate(normal.gram):  # each m's Gram padded to the block's size, in the accumulation's precision
        pad = np.zeros((1, n0, n0), gdt)
        pad[0, :len(g), :len(g)] = g
        ctx.write(out, name, (slice(k, k + 1),), pad)
    return {"baselines": int(len(keep)), "m": [m0, m1], "eps": list(stokes_eps(cfg.imaging.eps, cfg.imaging.eps_pol)),
            "stokes_lmax": lmax_p}


def _block_mmodes(ctx, fi, m_range, keep, dtype):
    """The block's m-modes ``(split, m of m_range, pm, corr, baselines keep)`` of channel ``fi`` in ``dtype`` (the
    transfer's precision, in which :func:`block_normal` uses them), read one baseline chunk of the store at a
    time: the block's complex128 m-modes are never held whole (:func:`blocks.mmode_bytes_per_m`)."""
    arr = ctx.open(STORES.mmodes)[STORES.mmodes.mmodes_corr]
    ch, (m0, m1) = arr.chunks[-1], m_range
    out = np.empty((arr.shape[0], m1 - m0) + arr.shape[3:5] + (len(keep),), dtype)
    for c0 in range(0, arr.shape[-1], ch):
        cols = np.flatnonzero((keep >= c0) & (keep < c0 + ch))
        if len(cols):
            part = ctx.read(STORES.mmodes.mmodes_corr, (slice(None), slice(fi, fi + 1), slice(m0, m1), slice(None),
                                                        slice(None), slice(c0, c0 + ch)))
            out[..., cols] = part[:, 0][..., keep[cols] - c0]
    return out


def block_normal(cfg, tel, freq, pairs, mm, w, m_range, timings=None, grids=None):
    """The normal equations of one block of m ``m_range`` (:func:`accumulate_polarised_normal`, float32 or
    float64 as ``transfer.dtype``) of baselines ``pairs`` at ``freq`` (Hz) with their m-modes ``mm`` ``(split, m
    of the block, 2, corr, bl)`` and weights ``w`` ``(corr, bl)``, each chunk on its own grid (:func:`_grids`;
    ``grids`` wraps it: ``mmflow bench stokes-block`` times it); ``timings`` as there."""
    lmax, lmax_p = cfg.mmode.lmax, stokes_lmax_of(cfg)
    b = baselines_in_wavelengths(tel, pairs, freq)
    lmax_b = tel.baseline_lmax(freq, lmax, pairs) if cfg.transfer.per_baseline_lmax else None
    dtype = np.float32 if cfg.transfer.dtype == "float32" else np.float64
    grid_of = _grids(tel.lat_rad, make_jones(cfg.beam.model_dump()), freq, lmax, np.linalg.norm(b, axis=1))
    return accumulate_polarised_normal(grid_of if grids is None else grids(grid_of), b, mm, w, CORRELATIONS,
                                       dtype=dtype, lmax_b=lmax_b, lmax_p=lmax_p, m_range=m_range, lmax=lmax,
                                       timings=timings)


def block_solve(cfg, normal):
    """The solve of a block's data splits and the leakage of its unpolarised sky
    (:meth:`PolarisedObserver.solution_and_leakage`: each m factorised once, one m's factor in memory at a time)
    with ``eps``, ``eps_pol`` and the m-filters of ``imaging``."""
    eps, filters = stokes_eps(cfg.imaging.eps, cfg.imaging.eps_pol), m_filters(cfg.imaging)
    return PolarisedObserver(normal, eps, filters, keep_factors=False).solution_and_leakage()


def _grids(lat_rad, jones, freq, lmax, b_len):
    """``(top, index) -> PolarisedGrid`` of a chunk: exact to its ``top`` and its baselines' fringe band
    limit (both rounded up as :meth:`mmflow.mmode.engine.GridCache.key` rounds them: neighbouring chunks
    share a grid), the last one kept."""
    cache = {}

    def grid_of(top, index):
        key = GridCache.key(top, fringe_bandlimit(b_len[index], jones.lmax_hint), lmax)
        if key not in cache:
            cache.clear()
            cache[key] = make_polarised_grid(lat_rad, jones, freq, *key)
        return cache[key]
    return grid_of


class _StoredGrams:
    """The stored Grams of one frequency as a sequence over m (read one m at a time, complex128)."""

    def __init__(self, ctx, fi, blocks, sizes):
        self.ctx, self.fi, self.blocks, self.sizes = ctx, fi, blocks, sizes
        self.n = blocks[-1][1]

    def __len__(self):
        return self.n

    def __getitem__(self, m):
        m0 = max(b0 for b0, _ in self.blocks if b0 <= m)
        n = self.sizes(m)
        g = self.ctx.read(STORES.stokes.gram(self.fi, m0), (slice(m - m0, m - m0 + 1),))[0]
        return g[:n, :n].astype(np.complex128)


def _channel_task(ctx, key):
    """Phase two of one frequency: the polarisation response, the CLEAN of the sources and the CLEAN of V
    (module docstring)."""
    cfg = ctx.cfg
    fi, lmax, lmax_p = key.freq, cfg.mmode.lmax, stokes_lmax_of(cfg)
    n_split, n_bl = _split_baselines(ctx)
    sizes = sizes_of(cfg)
    grams, kept = _StoredGrams(ctx, fi, blocks_of(cfg, n_split, n_bl), sizes), kept_in_memory(cfg)
    if kept:  # each m's Gram read once: every observation of a sky (response, PSF tables, CLEAN cycles) takes it
        grams = [grams[m] for m in range(len(grams))]
    normal = PolarisedNormal(lmax, grams, None, None, lmax_p)
    eps, filters = stokes_eps(cfg.imaging.eps, cfg.imaging.eps_pol), m_filters(cfg.imaging)
    # every factor kept where a channel's fit; else the largest within FACTORS_KEPT_BYTES, the rest made per observation
    keep = range(len(grams)) if kept else factors_kept(cfg)
    observe = PolarisedObserver(normal, eps, filters, keep_factors=keep)
    tel = ctx.telescope()
    info = {"polarisation": polarisation_response(observe, _response_decs(tel.lat_rad)), "factors_kept": len(keep)}
    stored = ctx.read(STORES.stokes.alm, (slice(None), slice(fi, fi + 1)))[:, 0]  # (split, 4, m, l)
    splits = np.array([[healpy_alm(x, lmax) for x in a] for a in stored])  # (split, 4, n_alm)
    freq = float(ctx.open(STORES.vis)[STORES.vis.freqs_hz][fi])
    out = ctx.open(STORES.stokes, mode="r+")
    info["sources"] = _clean_sources(ctx, out, fi, freq, splits, tel.lat_rad, observe)
    if cfg.clean.enabled:
        info["v_clean"] = _clean_v(ctx, out, fi, freq, normal, eps, filters, splits, tel.lat_rad, observe)
    return info


#: the sources a channel's summary lists (the brightest in I)
MAX_SOURCES = 50


def _threshold_noise(ctx, fi, freq, splits, lat_rad, row):
    """``(threshold, noise)`` of a CLEAN selecting on Stokes ``row``'s peaks (Jy/sr or None): ``clean.threshold``
    if set; the map's jackknife sigma over the sky CLEAN sees where ``mmode.splits`` make one (the Stokes-I
    CLEAN's estimator: I and V are spin 0), for ``clean.threshold_sigma`` x it; None: the CLEAN's default (the
    dirty map's robust rms)."""
    cfg = ctx.cfg
    c, lmax = cfg.clean, cfg.mmode.lmax
    thr = None if c.threshold is None else float(units.convert(c.threshold, c.threshold_unit, "Jy/sr", freq))
    jk, names, nside = jackknife_splits(ctx, fi), list(cfg.mmode.splits), clean_nside(cfg)
    noise = None if jk[0] is None else jackknife_sigma({s: splits[names.index(s)][row] for s in jk[1]}, jk, lmax,
                                                       nside, observed_mask(nside, never_seen_dec_min(lat_rad)))
    return thr, noise


def _clean_sources(ctx, out, fi, freq, splits, lat_rad, observe):
    """The full-Stokes CLEAN of the compact sources of the full data ``splits[0]``
    (:func:`mmflow.imaging.polarised_clean.clean_stokes` on I's peaks, the ``clean`` settings, its threshold
    from I's noise as :func:`_threshold_noise`) and its sources (:func:`~mmflow.imaging.polarised_clean.stokes_sources`,
    frame of date; the products stage states them in ``products.frame``), written to ``stokes.zarr``'s ``src_*``
    (the residual, the components per cycle, the I PSF table) for the restored maps."""
    cfg = ctx.cfg
    thr, noise = _threshold_noise(ctx, fi, freq, splits, lat_rad, I)
    table = psf_table(observe, np.deg2rad(_source_decs(ctx)), beam=I)
    # on I's positive peaks only, whatever clean.absolute (the Stokes-I clean stage's): a compact source's I is
    # positive, and with m = 0 filtered (imaging.filter_m0) each source's PSF has a negative ring along its
    # declination, on which |I| ranking placed negative components that no source's sum holds: I 4-11 % low and
    # an unpolarised source's Q, U, V 1 % of I on independent data, 0.3-0.7 % and 0.25 % with positive peaks
    # (tests/workflow/test_stokes_independent.py)
    opts = dataclasses.replace(clean_options(cfg.clean), absolute=False)
    res = clean_stokes(observe, splits[0], lat_rad, opts, clean_nside(cfg), thr, noise, table)
    # the stated sources; the restored maps then hold their vectors, not the residual's shrunken Q, U, V
    sources = close_sources(observe, res, max_sources=MAX_SOURCES)
    s, one, n_m = STORES.stokes, (slice(fi, fi + 1),), out[STORES.stokes.alm].shape[3]
    ctx.write(out, s.src_residual, one, padded_alm(res["residual"], cfg.mmode.lmax, n_m)[None])
    ctx.write(out, s.src_psf_table, one, psf.table_to_array(table)[None], allow_nan=True)
    for cyc in range(res["cycles"]):  # one chunk per cycle run
        sel = res["cycle"] == cyc
        comps = np.zeros((1, 1, cfg.clean.peaks_per_cycle, 7))
        comps[0, 0, :sel.sum()] = np.c_[res["vec"][sel], res["stokes"][sel]]
        ctx.write(out, s.src_components, (slice(fi, fi + 1), slice(cyc, cyc + 1)), comps)
    ctx.write(out, s.src_n_cycles, one, np.array([res["cycles"]]))
    return {"cycles": int(res["cycles"]), "components": int(len(res["stokes"])), "stop": res["reason"],
            "threshold_jy_sr": float(res["threshold"]), "noise_jy_sr": float(res["noise"]), "cond_max": COND_MAX,
            "frame": "date", "sources": sources}


def _clean_v(ctx, out, fi, freq, normal, eps, filters, splits, lat_rad, observe):
    """The CLEAN of V (:func:`mmflow.imaging.polarised_clean.clean_stokes_v`) of the full data ``splits[0]``
    with the ``clean`` settings: ``clean.threshold`` if set, else ``clean.threshold_sigma`` x the V map's
    noise: its jackknife sigma where ``mmode.splits`` make one (as the Stokes-I CLEAN), else the dirty V
    map's robust rms (:func:`_threshold_noise`)."""
    cfg = ctx.cfg
    c, lmax, n_m = cfg.clean, cfg.mmode.lmax, out[STORES.stokes.alm].shape[3]
    thr, noise = _threshold_noise(ctx, fi, freq, splits, lat_rad, V)
    table = v_psf_table(normal, eps, np.deg2rad(_v_decs(ctx)), filters, observe)
    res = clean_stokes_v(normal, eps, splits[0], lat_rad, clean_options(c), clean_nside(cfg), filters, thr, table,
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
    next_cycle=_next_cycle,
    enabled=lambda cfg: is_full_stokes(cfg.imaging.stokes),
    description="full-Stokes transfer coefficients (E-field beam), normal equations over T, E, B, V and "
    "Tikhonov per Stokes, per frequency and block of m; leakage of the unpolarised sky; then per frequency "
    "the polarisation response and the CLEAN of V (clean.enabled)",
    cost=COST,
    reads={STORES.vis: VIS_METADATA, STORES.mmodes: ("mmodes_corr", "inv_var_corr", "inv_var", "n_samples")},
)
