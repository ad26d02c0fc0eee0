"""The ``models`` stage (solve): resolved source models fitted from the calibrated data.

Paper section 3.5: Cyg A and Cas A are marginally resolved by the OVRO-LWA, and a point model
peels them only so far. Tasks ``f{F}_s{S}`` fit ``models.components[source]`` elliptical
Gaussian components to source ``S`` of ``models.sources`` in channel ``F``:

1. the integrations where the source is above ``models.min_elevation_deg`` (refused before any
   task, naming ``models.min_track_min``, when they last less than that), at most
   ``models.max_integrations`` of them evenly spaced, read calibrated (:func:`read_block`:
   the corrections of the stages before this one);
2. every source of ``peel.sources`` and ``peel.model_sources`` gets a flux per integration by
   weighted least squares on its catalogue coherency
   (:func:`mmflow.calibrate.source_models.fit_fluxes`); all but the fitted one are subtracted;
3. with ``models.recentre`` the source is moved back, per integration, to its catalogued
   position (the matched-filter offset of :func:`fit_point_position`), so that ionospheric
   refraction is not fitted as structure;
4. :func:`mmflow.calibrate.source_models.fit_gaussian_components` (Nelder-Mead) minimises the
   residual variance of the dirty image in an aperture around the source over all those
   integrations phased up, each integration's model scaled by its own least-squares amplitude
   (scintillation), from a symmetric start of the source's size (``models.size_arcmin``), and
   the fluxes are renormalised to the published spectrum.

The aperture radius defaults to twice the fringe spacing of the longest baseline used (at
least twice the start's extent): an aperture much smaller than the synthesised beam measures one
number, the residual at the centre, and leaves the shape unconstrained.

Offsets are east/north on the tangent plane of the frame of date;
:func:`mmflow.workflow.engine.peel_models.fitted_sources` turns
them into :class:`mmflow.sky.sources.Source` components (east/north of the ICRS position: the
frames' north differ by < 0.1 deg, < 0.01' on these offsets). ``models.zarr`` (see
:func:`mmflow.io.calibration_stores.models_store`) is read by the peel stage, which copies the fits into
``peel.zarr``'s attributes
(:func:`mmflow.workflow.engine.peel_models.fitted_tables`) for its tasks and its ``apply`` alike.
"""
from __future__ import annotations

import numpy as np

from mmflow.calibrate.coherency import apparent_flux, source_coherencies, source_vector_date
from mmflow.calibrate.source_models import (ARCMIN, GaussianComponent, fit_fluxes, fit_gaussian_components,
                                            fit_point_position, pack_components, source_uvw, symmetric_start)
from mmflow.errors import InputError
from mmflow.io.calibration_stores import MODEL_COLUMNS, models_store
from mmflow.io.run_stores import STORES
from mmflow.sky.sources import epoch_year, get_sources
from mmflow.conventions import SPEED_OF_LIGHT
from mmflow.workflow.engine.baseline_cuts import solve_mask
from mmflow.workflow.engine.blocks import read_block
from mmflow.workflow.engine.chunking import TIME_CHUNK
from mmflow.workflow.stages.models.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey

DEFAULT_SIZE_ARCMIN = 3.0


def _epoch(ctx):
    return float(ctx.vis_attrs()["epoch_jd"])


def _track(ctx, tel, lst, name):
    """Rows (sorted) where source ``name`` is above ``models.min_elevation_deg``, and their length (min)."""
    good = np.isfinite(lst)
    _, elev = apparent_flux(tel, float(tel.freqs_hz[0]), np.where(good, lst, 0.0), get_sources([name]), _epoch(ctx))
    rows = np.flatnonzero(good & (np.rad2deg(elev[0]) >= ctx.cfg.models.min_elevation_deg))
    return rows, len(rows) * float(ctx.vis_attrs()["integration_s"]) / 60.0


def _prepare(ctx):
    m = ctx.cfg.models
    vg = ctx.open(STORES.vis)
    nf = vg[STORES.vis.vis].shape[2]
    tel = ctx.telescope()
    lst = vg[STORES.vis.lst][:]
    for name in m.sources:  # refuse before any work
        _, minutes = _track(ctx, tel, lst, name)
        if minutes < m.min_track_min:
            raise InputError(str(ctx.run.store(STORES.vis)), "models.min_track_min",
                             f"{name} is above {m.min_elevation_deg:g} deg elevation for {minutes:.1f} min of the "
                             f"data, less than models.min_track_min = {m.min_track_min:g} min",
                             "give data covering a longer track, or lower models.min_track_min or "
                             "models.min_elevation_deg (a short track does not smear the rest of the sky out)")
    n_comp = [int(m.components.get(n, 1)) for n in m.sources]
    ctx.create(models_store(nf, len(m.sources), max(n_comp),
                            {"sources": list(m.sources), "n_components": n_comp, "columns": list(MODEL_COLUMNS)}))
    return [TaskKey(freq=fi, source=s) for fi in range(nf) for s in range(len(m.sources))]


def _read_rows(ctx, rows, fi):
    """Calibrated data of channel ``fi`` at the given rows (read chunk by chunk: never the whole day at
    once), ``(vis, weights)`` (time, bl, pol), ``lst`` and the pairs."""
    parts = []
    for c in np.unique(rows // TIME_CHUNK):
        sel = rows[rows // TIME_CHUNK == c]
        block = read_block(ctx, slice(int(sel[0]), int(sel[-1]) + 1), channels=slice(fi, fi + 1))
        k = sel - sel[0]
        parts.append((block.vis[k, :, 0], block.weights[k, :, 0], block.lst[k]))
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]), block.pairs)


def _task(ctx, key):
    m, p = ctx.cfg.models, ctx.cfg.peel
    fi, si = key.freq, key.source
    name = m.sources[si]
    tel = ctx.telescope()
    f = float(tel.freqs_hz[fi])
    rows, _ = _track(ctx, tel, ctx.open(STORES.vis)[STORES.vis.lst][:], name)
    rows = rows[np.unique(np.linspace(0, len(rows) - 1, min(len(rows), m.max_integrations)).round().astype(int))]
    vis, weights, lst, pairs = _read_rows(ctx, rows, fi)
    keep = solve_mask(tel, pairs, p.min_baseline_lambda, f) & (pairs[:, 0] != pairs[:, 1])
    w = weights.min(-1) * keep
    data = vis.mean(-1)  # unpolarised: the mean of the polarisations
    # every removed and modelled source with a flux per integration; all but this one subtracted
    names = [name] + [n for n in list(p.sources) + list(p.model_sources) if n != name]
    srcs = get_sources(names)
    total = float(srcs[0].flux(f, epoch_year(_epoch(ctx))))
    coh = source_coherencies(tel, f, lst, srcs, _epoch(ctx), pairs)
    unit = coh / np.array([float(s.flux(f, epoch_year(_epoch(ctx)))) for s in srcs])[:, None, None]
    scale = fit_fluxes(data, w, unit)  # (time, source)
    data = data - np.einsum("ts,stb->tb", scale[:, 1:], unit[1:])
    vec = source_vector_date(srcs[0], _epoch(ctx))
    uvw, beam = source_uvw(tel, f, lst, pairs, vec)
    if m.recentre:  # the source back at its catalogued position in every integration
        off, _ = fit_point_position(data, w, uvw)
        data = data * np.exp(-2j * np.pi * (uvw[..., 0] * off[:, :1] + uvw[..., 1] * off[:, 1:]))
    size = float(m.size_arcmin.get(name, DEFAULT_SIZE_ARCMIN))
    start = symmetric_start(int(m.components.get(name, 1)), size, total)
    longest = np.linalg.norm(tel.baselines_enu(pairs)[keep], axis=1).max() * f / SPEED_OF_LIGHT
    aperture = m.aperture_arcmin or max(2 / longest / ARCMIN, 2 * 0.75 * size)
    step = m.step_arcmin or aperture / 8
    point = [GaussianComponent(0.0, 0.0, total, 0.0, 0.0, 0.0)]
    _, res_point = fit_gaussian_components(data, w, uvw, beam, point, aperture_arcmin=aperture, step_arcmin=step,
                                           free_amplitudes=True, maxiter=1)
    comps, res = fit_gaussian_components(data, w, uvw, beam, start, aperture_arcmin=aperture, step_arcmin=step,
                                         reference_flux=total, free_amplitudes=True, maxiter=m.maxiter)
    g = ctx.open(STORES.models, mode="r+")
    n_max = g[STORES.models.components].shape[2]
    table = np.zeros((n_max, len(MODEL_COLUMNS)))
    table[:len(comps)] = pack_components(comps).reshape(len(comps), -1)
    region = (slice(fi, fi + 1), slice(si, si + 1))
    ctx.write(g, STORES.models.components, region, table[None, None])
    ctx.write(g, STORES.models.cost, region, np.array([[[res_point["fun_start"], res["fun_start"], res.fun]]]))
    ctx.write(g, STORES.models.iterations, region, np.array([[int(res.nit)]]))
    ctx.write(g, STORES.models.n_integrations, region, np.array([[len(rows)]]))
    return {
        "fits": 1,
        "iterations": int(res.nit),
        "improvement_db": float(10 * np.log10(res.fun / res_point["fun_start"])),
    }


STAGE = Stage("models", ("models", "peel.sources", "peel.model_sources", "peel.min_baseline_lambda", "beam"),
               (STORES.vis, STORES.gains), (STORES.models,), _prepare, _task, kind="solve",
               enabled=lambda cfg: cfg.models.enabled, counters=("fits",),
               description="resolved source models (Gaussian components) fitted to the calibrated data", cost=COST)
