"""The ``products`` stage (per frequency): maps, plots and summaries.

It rotates the solved alm to ``products.frame`` at the *data's* epoch (stored with the
visibilities) and writes ``maps/map_<MHz>MHz.fits`` (never-seen sky UNSEEN), PNGs and
summaries; with ``clean.enabled`` also the restored, residual, model and noise maps, PSF
stamps and Table 1 (:mod:`mmflow.workflow.stages.products.clean`); the flux scale, astrometric
registration and spectral-index products (:mod:`mmflow.workflow.stages.products.science`). ``summary_<tag>.json``
and ``summary.json`` hold what a report needs (paths, PSF FWHMs, noise, CLEAN history,
Table-1 rows); with ``imaging.stokes: [I, Q, U, V]`` the full-Stokes maps
(:mod:`mmflow.workflow.stages.products.stokes`). Only the files it lists are ever removed.
"""
from __future__ import annotations

import json
import time

import numpy as np

from mmflow.conventions import SPEED_OF_LIGHT, healpy_alm, is_full_stokes
from mmflow.imaging import maps as imaging_maps
from mmflow.imaging.lcurve import lcurve_corner
from mmflow.imaging.sky_mask import observed_sky_mask
from mmflow.io.export import write_healpix_fits, write_lcurve_png, write_mollweide_png, write_table1
from mmflow.io.report import summary_from_run, write_report
from mmflow.sky.frames import rotation_matrix
from mmflow.workflow.engine.geometry import mmax_of
from mmflow.workflow.engine.resources import gb, peak_rss_bytes
from mmflow.workflow.stages.products.clean import clean_history_figure, clean_products, table1_row
from mmflow.workflow.stages.products.science import channel_science, finalize_science
from mmflow.workflow.stages.products.stokes import stokes_products
from mmflow.workflow.stages.products.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey
from mmflow.io.run_stores import VIS_METADATA, STORES


def frequency_tags(freqs_hz):
    """``'40.000MHz'``-style names, with as many decimals (>= 3) as make every channel's unique."""
    mhz = np.asarray(freqs_hz, float) / 1e6
    for decimals in range(3, 10):
        tags = [f"{f:.{decimals}f}MHz" for f in mhz]
        if len(set(tags)) == len(tags):
            return tags
    raise ValueError(f"duplicate frequencies {mhz.tolist()} MHz")


def _products_prepare(ctx):
    (ctx.run.path / "maps").mkdir(parents=True, exist_ok=True)
    return [TaskKey(freq=fi) for fi in range(ctx.open(STORES.alm)[STORES.alm.alm].shape[1])]


def _products_task(ctx, key):
    cfg = ctx.cfg
    fi = key.freq
    vis = ctx.open(STORES.vis)
    freqs = vis[STORES.vis.freqs_hz][:]
    f, epoch, lat = float(freqs[fi]), float(vis.attrs["epoch_jd"]), float(vis.attrs["lat_deg"])
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    alm = healpy_alm(ctx.read(STORES.alm.alm, (slice(0, None), slice(fi, fi + 1)))[0, 0], lmax, mmax)
    lc = ctx.read(STORES.alm.lcurve, (slice(fi, fi + 1),))[0].sum(axis=0)
    frac = ctx.read(STORES.alm.fraction_above, (slice(fi, fi + 1),))[0]
    eps = ctx.read(STORES.alm.eps_grid)
    p = cfg.products
    nside = p.nside or 2 * imaging_maps.default_nside(lmax)
    # through the module: tests/acceptance/test_faults.py replaces alm_to_output_map there
    hmap = imaging_maps.alm_to_output_map(alm, lmax, f, epoch, p.frame, p.unit, nside)
    ctx.check_finite(f"maps/map of channel {fi}", hmap)
    mask = observed_sky_mask(nside, lat, None if p.frame == "date" else rotation_matrix(p.frame, "date", epoch))
    tag = frequency_tags(freqs)[fi]
    maps = ctx.run.path / "maps"
    meta = {"FREQ": f, "LMAX": lmax, "EPS": cfg.imaging.eps, "METHOD": cfg.imaging.method, "BUNIT": p.unit,
            "COORDSYS": {"icrs": "C", "galactic": "G", "date": "C"}[p.frame], "EPOCHJD": epoch,
            # Stokes I with I = (XX + YY) / 2 (pyuvdata's 'avg'); POLIN: the input's convention (docs/conventions.md)
            "STOKES": "I", "POLCONV": "avg", "POLIN": str(vis.attrs.get("pol_convention", "avg"))}
    write_healpix_fits(maps / f"map_{tag}.fits", hmap, meta, mask=mask)
    ctx.ledger.record_file(maps / f"map_{tag}.fits")
    seen = hmap[mask]
    info = {"freq_hz": f, "fits": f"maps/map_{tag}.fits", "nside": nside, "unit": p.unit, "frame": p.frame,
            "epoch_jd": epoch, "resolution_deg": _resolution_deg(vis, f, lmax), "sky_fraction_seen": float(mask.mean()),
            "map_min": float(seen.min()), "map_max": float(seen.max()), "map_rms": float(seen.std()),
            "fraction_singular_values_above_sqrt_eps": float(np.mean(frac)),
            "lcurve_corner_eps": lcurve_corner(lc[:, 0], lc[:, 1], eps) if lc.any() else None}
    if p.png:
        write_mollweide_png(maps / f"map_{tag}.png", hmap, f"mmflow {tag} ({p.frame}, {p.unit})", p.unit,
                            mask=mask, lmax=lmax, eps=cfg.imaging.eps, freq_hz=f,
                            resolution_deg=info["resolution_deg"], frame=p.frame)
        ctx.ledger.record_file(maps / f"map_{tag}.png")
        info["png"] = f"maps/map_{tag}.png"
        if lc.any():
            info["chosen_over_corner_eps"] = write_lcurve_png(
                maps / f"lcurve_{tag}.png", lc, eps, cfg.imaging.eps, corner=info["lcurve_corner_eps"], freq_hz=f,
                weighted=cfg.transfer.noise_weighting)
            ctx.ledger.record_file(maps / f"lcurve_{tag}.png")
    if is_full_stokes(cfg.imaging.stokes):
        info["stokes"] = stokes_products(ctx, fi, tag, nside, mask, meta, p.png)
    if cfg.clean.enabled:
        info.update(clean_products(ctx, fi, tag, f, epoch, nside, mask, meta, p.png))
        info["table1"] = table1_row(ctx, fi, f, info)

    info.update(channel_science(ctx, fi, tag, f, epoch, hmap, nside))
    (maps / f"summary_{tag}.json").write_text(json.dumps(info, indent=2))
    ctx.ledger.record_file(maps / f"summary_{tag}.json")
    return info


def _resolution_deg(vis, freq_hz, lmax):
    """The finer of the lmax limit (180 / lmax degrees) and the longest baseline's lambda / b."""
    enu, pairs = vis[STORES.vis.antenna_enu][:], vis[STORES.vis.pairs][:]
    b_max = float(np.linalg.norm(enu[pairs[:, 1]] - enu[pairs[:, 0]], axis=1).max())
    return float(max(180.0 / lmax, np.degrees(SPEED_OF_LIGHT / freq_hz / b_max) if b_max > 0 else 0.0))


#: per stage in maps/summary.json's ``stages``: what the stage cost
COST_KEYS = ("wall_s", "tasks", "tasks_run", "task_s", "worker_peak_rss_gb", "driver_peak_rss_gb", "bytes_written")


def _cost_so_far(ctx):
    """This stage's :data:`COST_KEYS` as the report is written, before the stage completes: its tasks (each
    one's recorded seconds and worker peak), wall time since the runner began it (its ``_prepare`` marker),
    the driver's peak so far and the maps written so far; ``until`` says where the count stops."""
    run = ctx.run
    infos = list(run.task_infos("products").values())
    peaks = [i["peak_rss_gb"] for i in infos if i.get("peak_rss_gb") is not None]
    began = run.marker("products", "_prepare")
    return {"wall_s": round(time.time() - began.stat().st_mtime, 2) if began.exists() else None,
            "tasks": len(infos), "tasks_run": len(infos), "task_s": round(sum(i.get("seconds", 0) for i in infos), 3),
            "worker_peak_rss_gb": max(peaks) if peaks else None, "driver_peak_rss_gb": gb(peak_rss_bytes()),
            "bytes_written": run.bytes_of(["maps"]), "until": "the report"}


def _products_finalize(ctx):
    maps = ctx.run.path / "maps"
    tags = frequency_tags(ctx.open(STORES.vis)[STORES.vis.freqs_hz][:])
    parts = [json.loads((maps / f"summary_{t}.json").read_text()) for t in tags]
    out = {"maps": parts}
    if ctx.cfg.clean.enabled:
        rows = [p["table1"] for p in parts]
        out["table1"] = {"rows": rows, "files": [f"maps/{q.name}" for q in write_table1(maps, rows)]}
        for q in out["table1"]["files"]:
            ctx.ledger.record_file(ctx.run.path / q)
        if ctx.cfg.products.png:
            out["clean_figure"] = clean_history_figure(ctx, parts, tags)

    out.update(finalize_science(ctx, parts, tags))
    # what each stage before this one cost (issue 21): the run records it, the map's summary keeps it
    out["stages"] = {name: {k: st.get(k) for k in COST_KEYS} for name, st in ctx.run.stage_summaries().items()}
    out["stages"]["products"] = _cost_so_far(ctx)
    (maps / "summary.json").write_text(json.dumps(out, indent=2))
    ctx.ledger.record_file(maps / "summary.json")

    missing = write_report(maps / "report.html", summary_from_run(ctx.run.path), ctx.run.path)
    ctx.ledger.record_file(maps / "report.html")
    return {"maps": len(parts), "report": "maps/report.html", "report_missing": missing}


STAGE = Stage("products", ("mmode.lmax", "mmode.mmax", "mmode.splits", "imaging", "products",
                            "transfer.noise_weighting", "transfer.m_block", "clean", "peel.enabled"),
               (STORES.vis, STORES.mmodes, STORES.normal, STORES.alm, STORES.stokes, STORES.clean, STORES.peel),
               ("maps",),
               _products_prepare, _products_task, _products_finalize,
               description="HEALPix FITS maps, Mollweide PNGs, L-curves, summary; CLEAN maps, PSF stamps, Table 1; "
               "flux scale, spectral index, astrometry; HTML report", cost=COST,
               reads={STORES.vis: VIS_METADATA, STORES.mmodes: ("n_samples",)})
