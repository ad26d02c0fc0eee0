"""Data stages: ``simulate`` (the demo's drift scan) and ``ingest`` (pyuvdata formats).

Both write ``vis.zarr``: ``vis`` (time, baseline, frequency) complex64 Stokes-I in Jy in
mmflow's sign convention, ``weights`` (0 = flagged), ``lst`` (rad), ``time_jd``,
``freqs_hz``, ``pairs`` and ``antenna_enu``; attributes hold the site, epoch and provenance.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import zarr

from mmflow.sky.frames import rotation_matrix
from mmflow.sky.sources import get_sources
from mmflow.workflow.context import SIDEREAL_DAY_S, build_telescope
from mmflow.workflow.stages.base import Stage, register

TIME_CHUNK = 256


def _create_vis_store(path, n_time, pairs, freqs, layout, attrs, bl_chunk, time_chunk=TIME_CHUNK):
    """Create the store once. Chunks are (time chunk, baseline chunk, all frequencies): a
    time-chunk task writes whole chunks of its rows; an m-mode task reads whole chunks of its
    baseline columns (the corner turn happens through storage, with bounded memory)."""
    g = zarr.open_group(str(path), mode="a")
    if "vis" in g:
        return g
    nbl, nf = len(pairs), len(freqs)
    ch = (time_chunk, min(bl_chunk, nbl), nf)
    g.create_array("vis", shape=(n_time, nbl, nf), chunks=ch, dtype="complex64", fill_value=0)
    g.create_array("weights", shape=(n_time, nbl, nf), chunks=ch, dtype="float32", fill_value=0)
    g.create_array("lst", shape=(n_time,), chunks=(time_chunk,), dtype="float64", fill_value=np.nan)
    g.create_array("time_jd", shape=(n_time,), chunks=(time_chunk,), dtype="float64", fill_value=np.nan)
    g.create_array("freqs_hz", data=np.asarray(freqs, float))
    g.create_array("pairs", data=np.asarray(pairs, "int32"))
    g.create_array("antenna_enu", data=np.asarray(layout.enu, float))
    g.attrs.update(dict(attrs, antenna_names=list(layout.names), lat_deg=layout.lat_deg, lon_deg=layout.lon_deg,
                        height_m=layout.height_m, layout_provenance=layout.provenance))
    return g


# ----------------------------------------------------------------------------- simulate

def _n_integrations(cfg):
    o = cfg.observation
    return o.n_integrations or int(round(SIDEREAL_DAY_S / o.integration_s))


def _sim_prepare(ctx):
    cfg = ctx.cfg
    tel = build_telescope(cfg)
    n = _n_integrations(cfg)
    _create_vis_store(ctx.run.store("vis.zarr"), n, tel.antenna_pairs(), tel.freqs_hz, tel.layout,
                      {"source": "simulate", "epoch_jd": cfg.observation.epoch_jd,
                       "sky": cfg.sky.model_dump(), "integration_s": cfg.observation.integration_s},
                      cfg.mmode.baseline_chunk)
    return [f"t{i:05d}" for i in range(-(-n // TIME_CHUNK))]


@lru_cache(maxsize=4)
def _sky_points(config_json, freq_hz):
    """The simulated sky at one frequency as weighted directions (frame of date)."""
    from mmflow.simulate.visibilities import SkyPoints, gauss_legendre_points
    from mmflow.sky.diffuse import synthetic_sky_kelvin
    from mmflow.sky.units import kelvin_to_jy_per_sr
    from mmflow.mmode.transfer import fringe_bandlimit
    from mmflow.workflow.context import _parse

    cfg = _parse(config_json)
    tel = build_telescope(cfg)
    epoch = cfg.observation.epoch_jd
    pts = SkyPoints(np.zeros((0, 3)), np.zeros(0))
    if cfg.sky.diffuse:
        lmax = cfg.sky.diffuse_lmax
        alm = kelvin_to_jy_per_sr(synthetic_sky_kelvin(freq_hz, lmax, epoch, seed=cfg.sky.seed), freq_hz)
        b = np.linalg.norm(tel.baselines_enu(), axis=1) * freq_hz / 299792458.0
        quad = lmax + fringe_bandlimit(b, tel.beam.lmax_hint) + cfg.sky.quad_oversample
        pts = pts + gauss_legendre_points(alm, lmax, quad)
    if cfg.sky.sources:
        srcs = get_sources(cfg.sky.sources)
        rot = rotation_matrix("icrs", "date", epoch)
        year = 2000.0 + (epoch - 2451545.0) / 365.25
        for src in srcs:
            vec, flux = src.points(freq_hz, year)
            pts = pts + SkyPoints(vec @ rot.T, flux)
    return pts


def _sim_task(ctx, key):
    from mmflow.simulate.visibilities import simulate_drift_scan, thermal_noise

    cfg = ctx.cfg
    tel = build_telescope(cfg)
    i = int(key[1:])
    n = _n_integrations(cfg)
    t0, t1 = i * TIME_CHUNK, min(n, (i + 1) * TIME_CHUNK)
    o = cfg.observation
    k = np.arange(t0, t1)
    lst = (np.deg2rad(o.start_lst_deg) + 2 * np.pi * k * o.integration_s / SIDEREAL_DAY_S) % (2 * np.pi)
    pairs = tel.antenna_pairs()
    vis = np.zeros((len(k), len(pairs), len(tel.freqs_hz)), np.complex64)
    rng = np.random.default_rng([cfg.sky.seed, i])  # deterministic per chunk
    if cfg.sky.noise:  # radiometer noise needs each baseline's two autocorrelations
        is_auto = pairs[:, 0] == pairs[:, 1]
        if not is_auto.any():
            from mmflow.errors import InputError

            raise InputError("workflow", "sky.noise", "thermal noise needs autocorrelations",
                             "set telescope.include_autos=true or sky.noise=false")
        ant_index = {int(p[0]): c for c, p in enumerate(pairs[is_auto])}
        col_i = [ant_index[int(p)] for p in pairs[:, 0]]
        col_j = [ant_index[int(p)] for p in pairs[:, 1]]
    for fi, f in enumerate(tel.freqs_hz):
        v = simulate_drift_scan(tel, f, lst, _sky_points(ctx.config_json, float(f)), pairs, np.complex64)
        if cfg.sky.noise:
            autos = np.real(v[:, is_auto])
            noise, _ = thermal_noise(v, autos[:, col_i], autos[:, col_j], tel.channel_width_hz, o.integration_s, rng)
            v = v + noise
        vis[:, :, fi] = v
    g = zarr.open_group(str(ctx.run.store("vis.zarr")), mode="r+")
    g["vis"][t0:t1] = vis
    g["weights"][t0:t1] = 1.0
    g["lst"][t0:t1] = lst
    g["time_jd"][t0:t1] = o.epoch_jd + (k - n / 2) * o.integration_s / 86400.0
    return {"integrations": int(len(k))}


register(Stage("simulate", ("telescope", "beam", "observation", "sky"), (), ("vis.zarr",),
               _sim_prepare, _sim_task, enabled=lambda cfg: cfg.source == "simulate",
               description="time-domain drift-scan simulation (independent of transfer matrices)"))


# ----------------------------------------------------------------------------- ingest

def _ingest_prepare(ctx):
    from mmflow.io.ingest import plan_ingest, write_plan

    plan = plan_ingest(ctx.cfg)
    tel = build_telescope(ctx.cfg, plan.layout)
    g = _create_vis_store(ctx.run.store("vis.zarr"), plan.n_time, plan.pairs, plan.freqs_hz, tel.layout,
                          {"source": "ingest", "epoch_jd": plan.epoch_jd, "files": plan.files,
                           "skipped_files": plan.skipped, "integration_s": plan.integration_s},
                          ctx.cfg.mmode.baseline_chunk)
    write_plan(g, plan)
    return [f"t{i:05d}" for i in range(-(-plan.n_time // TIME_CHUNK))]


def _ingest_task(ctx, key):
    from mmflow.io.ingest import ingest_time_chunk

    i = int(key[1:])
    return ingest_time_chunk(ctx.cfg, ctx.run.store("vis.zarr"), i * TIME_CHUNK, (i + 1) * TIME_CHUNK)


register(Stage("ingest", ("input", "telescope", "observation"), (), ("vis.zarr",),
               _ingest_prepare, _ingest_task, enabled=lambda cfg: cfg.source == "ingest",
               description="read UVH5 / uvfits / MS files with pyuvdata, fanned out over time chunks of files"))
