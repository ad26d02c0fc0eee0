"""The ``simulate`` stage: the demo's drift scan (what it shares with ``ingest``:
:mod:`mmflow.workflow.engine.data_stage`).

With ``sky.resolved`` Cyg A and Cas A are simulated as their Gaussian components
(:func:`mmflow.sky.sources.resolved`), sampled by Gauss-Hermite quadrature (:meth:`Source.points`).
With ``imaging.stokes: [I, Q, U, V]`` it writes the four linear correlations through the
E-field beam, the sources polarised as ``sky.polarised`` says, corrupted or not (gains per feed,
``corrupt.leakage`` D-terms; :func:`mmflow.simulate.scene.simulate_polarised_chunk`; docs/stokes.md).

A diffuse sky (``sky.diffuse``, unpolarised) is summed first at ``N = 2 L + 1 + margin``
sidereal angles only (tasks ``d{F}_t{B}``, ``diffuse.zarr``): its drift scan is a trigonometric
polynomial of degree ``L = sky.diffuse_lmax`` in the sidereal angle, so the time chunks (the second
phase) interpolate it exactly to their integrations (:mod:`mmflow.simulate.drift_modes`) and sum
only the catalogue's points themselves.

Both data stages write ``vis.zarr`` (declared in :mod:`mmflow.io.run_stores`): visibilities per
polarisation (Stokes I alone for a clean simulation; XX and YY for a corrupted one or as ingested) in
Jy in mmflow's sign convention, weights (0 = flagged), LSTs and times per integration, and
attributes with the site, the data's epoch, integration time and channel width.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from mmflow.calibrate.coherency import source_vector_date
from mmflow.conventions import drift_scan_lsts, drift_scan_times, is_full_stokes
from mmflow.io.raw_files import RAW_DIR, raw_path, write_raw_chunk
from mmflow.io.calibration_stores import diffuse_store
from mmflow.io.run_stores import STORES, vis_store
from mmflow.simulate.corrupt import day_corruptions, sun_points, utc_at_lsts
from mmflow.simulate.drift_modes import coefficients_from_samples, evaluate_drift, n_samples, sample_lsts
from mmflow.simulate.scene import (diffuse_columns, diffuse_points, drift_samples, joined, polarised_sky_points,
                                   polarised_source_points, simulate_chunk, simulate_polarised_chunk, sky_points,
                                   source_points_date, unpolarised)
from mmflow.sky.sources import get_sources, resolved
from mmflow.telescope.beam_factory import make_jones
from mmflow.workflow.engine.chunking import TIME_CHUNK, chunk_rows, time_keys
from mmflow.workflow.engine.context import build_telescope
from mmflow.workflow.engine.data_stage import layout_attrs, write_autos
from mmflow.workflow.engine.geometry import DIFFUSE_SAMPLE_BLOCK, interpolates_diffuse, n_integrations
from mmflow.workflow.stages.simulate.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey


def _sim_prepare(ctx):
    cfg = ctx.cfg
    tel = build_telescope(cfg)
    n = n_integrations(cfg)
    o = cfg.observation
    full = is_full_stokes(cfg.imaging.stokes)
    attrs = dict(layout_attrs(tel.layout), source="simulate", epoch_jd=o.epoch_jd, sky=cfg.sky.model_dump(),
                 integration_s=o.integration_s, channel_width_hz=o.channel_width_khz * 1e3,
                 pols=["xx", "yy"] if cfg.corrupt.enabled or full else ["I"])
    if cfg.corrupt.enabled:
        attrs["corrupt"] = cfg.corrupt.model_dump()
    if full:  # the four correlations through the E-field beam, in mmflow's avg convention (I = (xx + yy) / 2)
        attrs.update(cross_pols=["xy", "yx"], pol_convention="avg")
    ctx.create(vis_store(n, tel.antenna_pairs(), tel.freqs_hz, tel.layout.enu, attrs, TIME_CHUNK,
                         cfg.mmode.baseline_chunk))
    if not interpolates_diffuse(cfg):
        return time_keys(n)
    # first phase: the diffuse sky at N sidereal angles, DIFFUSE_SAMPLE_BLOCK per task; then the time chunks
    n_s = n_samples(cfg.sky.diffuse_lmax)
    ctx.create(diffuse_store(len(tel.freqs_hz), n_s, len(tel.antenna_pairs()),
                             diffuse_columns(tel, cfg.corrupt.enabled, full), DIFFUSE_SAMPLE_BLOCK))
    return [TaskKey(phase="d", freq=fi, time=b) for fi in range(len(tel.freqs_hz))
            for b in range(-(-n_s // DIFFUSE_SAMPLE_BLOCK))]


def _next_cycle(ctx, cycle):
    """After the diffuse sky's samples, the time chunks (then done)."""
    return time_keys(n_integrations(ctx.cfg)) if cycle == 0 and interpolates_diffuse(ctx.cfg) else None


@lru_cache(maxsize=2)
def _skies(ctx):
    """The telescope, the sky per frequency (without the DD-corrupted sources) and, when the
    simulation is corrupted, per frequency the whole day's corruptions and the DD sources."""
    cfg = ctx.cfg
    tel = build_telescope(cfg)
    s, c, o = cfg.sky, cfg.corrupt, cfg.observation
    dd = list(c.dd_sources) if c.enabled else []
    model = resolved if s.resolved else (lambda src: src)  # sky.resolved: Cyg A, Cas A as Gaussian components
    plain = tuple(model(x) for x in get_sources([n for n in s.sources if n not in dd]))
    full = is_full_stokes(cfg.imaging.stokes)
    diffuse = s.diffuse_lmax if s.diffuse and not interpolates_diffuse(cfg) else None  # else: interpolated
    if full:
        skies = [polarised_sky_points(tel, float(f), o.epoch_jd, diffuse, s.seed, plain, s.polarised, s.quad_oversample)
                 for f in tel.freqs_hz]
    else:
        skies = [sky_points(tel, float(f), o.epoch_jd, diffuse, s.seed, plain, s.quad_oversample) for f in tel.freqs_hz]
    if not c.enabled:
        return tel, skies, None
    n = n_integrations(cfg)
    times_s = np.arange(n) * o.integration_s
    srcs = [model(x) for x in get_sources(dd)]
    vecs = np.array([source_vector_date(x, o.epoch_jd) for x in srcs]).reshape(-1, 3)
    corrupted = []
    for fi, f in enumerate(tel.freqs_hz):
        day = day_corruptions(tel.n_ant, float(f), times_s, len(srcs), tel.layout.enu,
                              np.random.default_rng([c.seed, fi]), gains=c.gains, sawtooth_db=c.sawtooth_db,
                              ionosphere_arcmin=c.ionosphere_arcmin, scintillation_sigma=c.scintillation,
                              crosstalk_jy=c.crosstalk_jy, rfi_jy=c.rfi_jy, leakage=c.leakage)
        points = [polarised_source_points(x, float(f), o.epoch_jd, s.polarised) if full
                  else source_points_date(x, float(f), o.epoch_jd) for x in srcs]
        corrupted.append((day, points, vecs))
    return tel, skies, corrupted


@lru_cache(maxsize=2)
def _jones(ctx):
    """The E-field beam of a full-Stokes simulation, built once per configuration (a beam file is read once)."""
    return make_jones(ctx.cfg.beam.model_dump())


def _diffuse_task(ctx, key):
    """The diffuse sky of channel ``key.freq`` at the sampled sidereal angles of block ``key.time``."""
    cfg = ctx.cfg
    tel = build_telescope(cfg)
    f = float(tel.freqs_hz[key.freq])
    s = cfg.sky
    lsts = sample_lsts(s.diffuse_lmax)[key.time * DIFFUSE_SAMPLE_BLOCK:(key.time + 1) * DIFFUSE_SAMPLE_BLOCK]
    points = diffuse_points(tel, f, cfg.observation.epoch_jd, s.diffuse_lmax, s.seed, s.quad_oversample)
    full = is_full_stokes(cfg.imaging.stokes)  # the four correlations through the E-field beam
    jones = _jones(ctx.for_stage(ctx.stage)) if full else None
    samples = drift_samples(tel, f, points, lsts, cfg.corrupt.enabled, jones)
    rows = slice(key.time * DIFFUSE_SAMPLE_BLOCK, key.time * DIFFUSE_SAMPLE_BLOCK + len(lsts))
    ctx.write(ctx.open(STORES.diffuse, mode="r+"), STORES.diffuse.samples, (slice(key.freq, key.freq + 1), rows),
              samples[None])
    return {"diffuse_samples": len(lsts)}


def _diffuse_at(ctx, lst):
    """Per channel the diffuse sky interpolated to the sidereal angles ``lst`` (``simulate_chunk``'s ``extra``)."""
    g = ctx.open(STORES.diffuse)
    out = []
    for fi in range(g[STORES.diffuse.samples].shape[0]):
        v = evaluate_drift(coefficients_from_samples(ctx.read(STORES.diffuse.samples, (slice(fi, fi + 1),))[0]),
                           lst, ctx.cfg.sky.diffuse_lmax)
        out.append(v[..., 0] if v.shape[-1] == 1 else v)
    return out


def _sim_task(ctx, key):
    if key.phase == "d":
        return _diffuse_task(ctx, key)
    cfg = ctx.cfg
    o = cfg.observation
    n = n_integrations(cfg)
    t0, t1 = chunk_rows(key, n)
    k = np.arange(t0, t1)
    tel, skies, corrupted = _skies(ctx.for_stage(ctx.stage))  # cached per configuration (no ledger)
    full = is_full_stokes(cfg.imaging.stokes)
    lst = drift_scan_lsts(np.deg2rad(o.start_lst_deg), o.integration_s, k)
    rng = np.random.default_rng([cfg.sky.seed, key.time]) if cfg.sky.noise else None  # fixed per chunk
    # the UTC at which the site's apparent LST is each integration's: near the day centred on the epoch
    time_jd = utc_at_lsts(lst, tel.layout, drift_scan_times(o.epoch_jd, o.integration_s, k[:1], n)[0])
    if cfg.sky.sun:  # the Sun moves ~1 deg a day against the stars: its position at the chunk's mid time

        mid = float(np.median(time_jd))
        sun = [sun_points(mid, float(f)) for f in tel.freqs_hz]
        skies = [joined([sky, unpolarised(x)]) if full else sky + x for sky, x in zip(skies, sun)]
    g = ctx.open(STORES.vis, mode="r+")
    rows = (slice(t0, t1),)
    if full:
        extra = _diffuse_at(ctx, lst) if interpolates_diffuse(cfg) else None
        vis, cross = simulate_polarised_chunk(tel, _jones(ctx.for_stage(ctx.stage)), lst, skies, rng, o.integration_s,
                                              corrupted, slice(t0, t1), cfg.corrupt.system_jy, extra)
        ctx.write(g, STORES.vis.vis_cross, rows, cross)
        ctx.write(g, STORES.vis.weights_cross, rows, np.ones(cross.shape, np.float32))
    else:
        extra = _diffuse_at(ctx, lst) if interpolates_diffuse(cfg) else None
        vis = simulate_chunk(tel, lst, skies, rng, o.integration_s, corrupted, slice(t0, t1), cfg.corrupt.system_jy,
                             extra)
    weights = np.ones(vis.shape, np.float32)
    if o.raw_files:
        _write_raw(ctx, tel, t0, time_jd, vis, cross if full else None)
    ctx.write(g, STORES.vis.vis, rows, vis)
    ctx.write(g, STORES.vis.weights, rows, weights)
    write_autos(ctx, g, rows, vis, weights)
    ctx.write(g, STORES.vis.lst, rows, lst)
    ctx.write(g, STORES.vis.time_jd, rows, time_jd)
    return {"integrations": int(len(k))}


def _write_raw(ctx, tel, t0, time_jd, vis, cross):
    """The chunk as the UVH5 file a telescope writes (``observation.raw_files``; :mod:`mmflow.io.raw_files`):
    XX, YY (and XY, YX of a full-Stokes simulation), recorded in the task's marker."""
    o = ctx.cfg.observation
    pols = ["xx", "yy"] + (["xy", "yx"] if cross is not None else [])
    data = vis if cross is None else np.concatenate([vis, cross], axis=-1)
    path = write_raw_chunk(raw_path(ctx.run_path, t0), tel, data, np.ones(data.shape, np.float32),
                           tel.antenna_pairs(), time_jd, tel.freqs_hz, pols, o.integration_s,
                           o.channel_width_khz * 1e3)
    ctx.ledger.record_file(path)


STAGE = Stage(
    "simulate",
    ("telescope", "beam", "observation", "sky", "corrupt", "mmode.baseline_chunk", "imaging.stokes"),
    (),
    (STORES.vis, STORES.diffuse, RAW_DIR),
    _sim_prepare,
    _sim_task,
    next_cycle=_next_cycle,
    enabled=lambda cfg: cfg.source == "simulate",
    description="time-domain drift-scan simulation (independent of transfer matrices), "
    "optionally corrupted (gains, DD effects, terrestrial signals); with imaging.stokes [I, Q, U, V] the four "
    "correlations of a polarised sky through the E-field beam",
    cost=COST,
)
