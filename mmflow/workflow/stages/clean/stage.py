"""The ``clean`` stage (iterative): m-mode CLEAN of every channel's Tikhonov map (docs/clean.md).

A thin adapter over :mod:`mmflow.imaging.clean` and :mod:`mmflow.imaging.psf`; every number is
computed by those kernels, this module only maps them over m blocks and cycles:

* prepare tasks, one per (frequency, m block): factorise ``G_kk + eps I`` from ``normal.zarr``
  (stored in ``clean.zarr`` when ``clean.keep_factors``), observe the point sources of the PSF
  declination grid (:func:`psf.psf_columns`), and write the dirty alm (``H dirty`` for a
  high-pass CLEAN) as the residual of cycle 0;
* ``next_cycle`` on the driver: at cycle 0 fit the PSF table (:func:`psf.fit_psf_columns`)
  and the jackknife noise and threshold (:mod:`mmflow.imaging.jackknife`, from the even and
  odd splits of ``alm.zarr``, else from its ``day<k>`` splits); then, per frequency not yet
  stopped (:func:`clean.stop_reason`), synthesise the residual map and pick this cycle's components
  (:func:`clean.plan_cycle`);
* cycle tasks, one per (frequency, m block): ``residual[c + 1] = residual[c] - observe(x)``
  (:func:`clean.observe_and_subtract`), ``x`` the block of the cycle's components' alm;
* finalize: the restored map (frame of date) per frequency.

Every cycle's residual and components go to their own chunks of ``clean.zarr`` (nothing is
rewritten), so a killed cycle is planned and run again identically from the one before.
"""
from __future__ import annotations

import time

import healpy
import numpy as np

from mmflow.conventions import m_blocks
from mmflow.imaging import clean as ck
from mmflow.imaging import psf
from mmflow.imaging.jackknife import beam_noise
from mmflow.io.run_stores import VIS_METADATA, STORES, CLEAN_STOPS, NOISE_FIELDS, clean_store
from mmflow.sky import units
from mmflow.workflow.engine.clean_state import (
    active,
    block_operators_from_gram,
    clean_nside,
    clean_options,
    clean_result,
    clean_table,
    cycle_block,
    factors_of,
    highpass,
    jackknife_sigma,
    jackknife_splits,
    psf_alm_columns,
    psf_decs_deg,
    residual_alm,
    split_alm,
    stored_operators,
)
from mmflow.workflow.engine.geometry import mmax_of
from mmflow.workflow.stages.clean.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey

CLEAN_CONFIG = ("mmode.lmax", "mmode.mmax", "mmode.splits", "transfer.m_block", "imaging", "clean")


def _lat(ctx):
    return float(ctx.vis_attrs()["lat_deg"])


def _geometry(ctx):
    cfg = ctx.cfg
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    return lmax, mmax, m_blocks(mmax, cfg.transfer.m_block)


# ----------------------------------------------------------------------------- prepare + tasks

def _prepare(ctx):
    cfg = ctx.cfg
    lmax, mmax, blocks = _geometry(ctx)
    nf = ctx.open(STORES.alm)[STORES.alm.alm].shape[1]
    n_dec = len(psf_decs_deg(_lat(ctx), cfg.clean.psf_dec_step_deg))
    ctx.create(clean_store(nf, lmax, mmax, cfg.transfer.m_block, n_dec, cfg.clean.max_cycles,
                           cfg.clean.peaks_per_cycle, 12 * clean_nside(cfg) ** 2, cfg.clean.keep_factors))
    return [TaskKey(freq=fi, m_block=m0) for fi in range(nf) for m0, _ in blocks]


def _ml_to_block(alm_ml, lmax, m0, m1):
    """Rows ``m0..m1-1`` of an (m, l) padded alm as the healpy-layout run of those m."""
    return np.concatenate([alm_ml[m - m0, m:] for m in range(m0, m1)])


def _task(ctx, key):
    if key.cycle is not None:
        return _cycle_task(ctx, key)
    return _setup_task(ctx, key)


def _setup_task(ctx, key):
    """Factorise, observe the PSF grid and write the residual of cycle 0, for one m block."""
    cfg = ctx.cfg
    fi, m0 = key.freq, key.m_block
    lmax, _, blocks = _geometry(ctx)
    m1 = dict(blocks)[m0]
    g = ctx.open(STORES.clean, mode="r+")
    t0 = time.perf_counter()
    ops = block_operators_from_gram(ctx, fi, m0, m1)
    t_factor = time.perf_counter() - t0
    if cfg.clean.keep_factors:
        ctx.write(g, STORES.clean.chol(fi, m0), (), factors_of(ops, lmax, m0, m1))
    t0 = time.perf_counter()
    decs = np.deg2rad(psf_decs_deg(_lat(ctx), cfg.clean.psf_dec_step_deg))
    ctx.write(g, STORES.clean.psf(fi, m0), (), psf.psf_columns(ops, lmax, psf.table_vectors(decs), m0, m1))
    t_psf = time.perf_counter() - t0
    dirty = _ml_to_block(ctx.read(STORES.alm.alm, (slice(0, 1), slice(fi, fi + 1), slice(m0, m1)))[0, 0],
                         lmax, m0, m1)
    w = highpass(cfg)
    if w is not None:
        dirty = dirty * np.concatenate([w[m:] for m in range(m0, m1)])
    ctx.write(g, STORES.clean.residual(fi, m0), (slice(0, 1),), dirty[None])
    return {"m": [m0, m1], "factor_s": round(t_factor, 4), "psf_s": round(t_psf, 4)}


def _cycle_task(ctx, key):
    """``residual[c + 1] = residual[c] - observe(x)`` for one (frequency, m block)."""
    cfg = ctx.cfg
    c, fi, m0 = key.cycle, key.freq, key.m_block
    lmax, _, blocks = _geometry(ctx)
    m1 = dict(blocks)[m0]
    t0 = time.perf_counter()
    ops = stored_operators(ctx, fi, m0, m1) if cfg.clean.keep_factors else block_operators_from_gram(ctx, fi, m0, m1)
    t_ops = time.perf_counter() - t0
    rows = ctx.read(STORES.clean.components, (slice(fi, fi + 1), slice(c, c + 1)))[0, 0]
    name = STORES.clean.residual(fi, m0)
    resid = ctx.read(name, (slice(c, c + 1),))[0]
    new, t = cycle_block(resid, rows, ops, lmax, m0, m1, highpass(cfg))
    ctx.write(ctx.open(STORES.clean, mode="r+"), name, (slice(c + 1, c + 2),), new[None])
    return {"m": [m0, m1], "operators_s": round(t_ops, 4), "components_s": round(t["components"], 4),
            "observe_s": round(t["observe"], 4)}


# ----------------------------------------------------------------------------- the driver


def _setup_tables(ctx, g):
    """Cycle 0 on the driver: PSF tables, jackknife noise and the stop threshold per frequency."""
    cfg = ctx.cfg
    c = cfg.clean
    lmax, mmax, blocks = _geometry(ctx)
    decs = np.deg2rad(psf_decs_deg(_lat(ctx), c.psf_dec_step_deg))
    w = highpass(cfg)
    nside = clean_nside(cfg)
    mask = ck.observed_mask(nside, ck.never_seen_dec_min(np.deg2rad(_lat(ctx))))
    freqs = ctx.read(STORES.vis.freqs_hz)
    for fi in range(g[STORES.clean.threshold].shape[0]):
        jk = jackknife_splits(ctx, fi)
        cols = psf_alm_columns(g, fi, lmax, blocks)
        tables = [psf.fit_psf_columns(cols, lmax, decs)]
        # the H PSF's columns weighted in place (the PSF's are not needed again): one copy of 0.6 GB at lmax 1000
        tables.append(tables[0] if w is None else psf.fit_psf_columns(psf.apply_l_weights(cols, lmax, w, out=cols),
                                                                      lmax, decs))
        del cols
        ctx.write(g, STORES.clean.psf_table, (slice(fi, fi + 1),),
                  np.stack([psf.table_to_array(t) for t in tables])[None], allow_nan=True)
        noise, sigma_clean = np.full(len(NOISE_FIELDS), np.nan), None
        if jk[0] is not None:
            alms = split_alm(ctx, fi, lmax, mmax)
            sigma_clean = jackknife_sigma(alms, jk, lmax, nside, mask)
            nz = beam_noise(sigma_clean, float(freqs[fi]), tables[0])
            noise = np.array([nz[k] for k in NOISE_FIELDS])
            if w is not None:  # CLEAN sees H maps: their noise sets its threshold
                sigma_clean = jackknife_sigma(alms, jk, lmax, nside, mask, w)
        ctx.write(g, STORES.clean.noise, (slice(fi, fi + 1),), noise[None], allow_nan=True)
        if c.threshold is not None:
            thr = float(units.convert(c.threshold, c.threshold_unit, "Jy/sr", float(freqs[fi])))
        else:
            thr = c.threshold_sigma * sigma_clean if sigma_clean is not None else 0.0
        ctx.write(g, STORES.clean.threshold, (slice(fi, fi + 1),), np.array([thr]))


def _next_cycle(ctx, cycle):
    cfg = ctx.cfg
    lmax, _, blocks = _geometry(ctx)
    g = ctx.open(STORES.clean, mode="r+")
    if cycle == 0:
        _setup_tables(ctx, g)
    opts, nside = clean_options(cfg.clean), clean_nside(cfg)
    mask = ck.observed_mask(nside, ck.never_seen_dec_min(np.deg2rad(_lat(ctx))))
    keys = []
    for fi in range(g[STORES.clean.threshold].shape[0]):
        thr = float(g[STORES.clean.threshold][fi])
        if not active(g[STORES.clean.peaks][fi, :cycle], thr, opts):
            continue
        vecs, flux, peak, _ = ck.plan_cycle(residual_alm(g, fi, cycle, lmax, blocks), lmax, clean_table(g, fi), mask,
                                            nside, opts, thr)
        rows = np.zeros((opts.n_peaks, 4))
        rows[:len(flux), :3], rows[:len(flux), 3] = vecs, flux
        ctx.write(g, STORES.clean.components, (slice(fi, fi + 1), slice(cycle, cycle + 1)), rows[None, None])
        ctx.write(g, STORES.clean.peaks, (slice(fi, fi + 1), slice(cycle, cycle + 1)), np.array([[peak]]))
        keys += [TaskKey(freq=fi, m_block=m0) for m0, _ in blocks]
    return keys or None


def _finalize(ctx):
    cfg = ctx.cfg
    lmax, mmax, blocks = _geometry(ctx)
    g = ctx.open(STORES.clean, mode="r+")
    opts, nside, w = clean_options(cfg.clean), clean_nside(cfg), highpass(cfg)
    out = {}
    for fi in range(g[STORES.clean.threshold].shape[0]):
        state, reason = clean_result(g, fi, opts)
        state.residual_alm = residual_alm(g, fi, state.cycle, lmax, blocks)
        table = clean_table(g, fi)
        if w is None:
            restored = ck.restore_map(healpy.alm2map(state.residual_alm, nside, lmax=lmax), state.comp_vec,
                                      state.comp_flux, table)
        else:
            restored = ck.restore_highpass(split_alm(ctx, fi, lmax, mmax)["full"], state, table, w, lmax, nside)
        ctx.write(g, STORES.clean.restored, (slice(fi, fi + 1),), restored[None])
        ctx.write(g, STORES.clean.n_cycles, (slice(fi, fi + 1),), np.array([state.cycle]))
        ctx.write(g, STORES.clean.stop, (slice(fi, fi + 1),), np.array([CLEAN_STOPS.index(reason) if reason else -1]))
        out[f"f{fi}"] = {"cycles": state.cycle, "stop": reason, "components": int(len(state.comp_flux)),
                         "first_peak_jy_sr": float(state.peaks[0]) if state.cycle else None,
                         "last_peak_jy_sr": float(state.peaks[-1]) if state.cycle else None,
                         "threshold_jy_sr": float(g[STORES.clean.threshold][fi])}
    return out


STAGE = Stage(
    "clean",
    CLEAN_CONFIG,
    (STORES.vis, STORES.mmodes, STORES.normal, STORES.alm),
    (STORES.clean,),
    _prepare,
    _task,
    _finalize,
    enabled=lambda cfg: cfg.clean.enabled,
    kind="iterative",
    next_cycle=_next_cycle,
    description="m-mode CLEAN: PSF by declination, major cycles over m blocks, jackknife threshold",
    cost=COST,
    reads={STORES.vis: VIS_METADATA, STORES.mmodes: ("n_samples",)},
)
