"""The ``peel`` stage (solve-then-apply): bright sources peeled or subtracted per integration.

Tasks ``f{F}_t{K}`` run over channels and time chunks of ``vis.zarr``. Each reads its
integrations calibrated (the corrections of the stages before it, :func:`read_block`), takes
the model coherency of every ``peel.sources`` source through the beam at the data's epoch
(:func:`mmflow.calibrate.coherency.source_coherencies`), chooses per integration whether a
source is peeled (``peel.peel``, above ``peel.peel_min_elevation_deg``), subtracted with a
fitted flux, or skipped (below the horizon) (:func:`select_modes`); the ``peel.model_sources``
are fitted with them (a flux scale per integration) and left in the data. It peels
(:func:`mmflow.calibrate.peel.peel`: direction-dependent gains per source, in flux order, for
``peel.passes`` passes; the guard subtracts instead where peeling removed less than
``peel.guard`` of the measured flux). ``peel.dd_model`` chooses the DD gains: ``screen`` (the
default) a refractive offset and a scintillation amplitude per source and integration
(:mod:`mmflow.calibrate.dd_screen`, the offset's phase per antenna from the source's sky
tangent plane at the data's epoch), ``antenna`` a free gain per antenna (Stefcal).
``peel.solint_s`` shares a peeled source's offset (or DD gains) over an interval (amplitude
still per integration); ``peel.fit_positions`` fits the
subtracted sources' positions per integration and peels again with the moved models.
``peel.zarr`` keeps per integration the DD gains (for a subtracted source: 1, or the phase
gradient of its fitted position), flux scales, modes, the guard's fluxes and convergence.

``apply`` subtracts, where a block is read, what peeling removed::

    V_ij -= sum_{s peeled} h_si conj(h_sj) M^s_ij + sum_{s subtracted} a_s h_si conj(h_sj) M^s_ij

(for a subtracted source ``h`` is 1, or with ``peel.fit_positions`` the phase gradient that
moves it to its fitted position in that integration)

with the same coherencies (recomputed for the block's baselines), so ``vis.zarr`` is never
rewritten.

With the ``models`` stage enabled, the sources it fitted are modelled by their fitted Gaussian
components (``models.zarr``) instead of the catalogue's points, in the solve and in ``apply``
alike: the peel stage copies them into ``peel.zarr``'s attribute ``fitted_models``, so ``apply``
(run by every later reader) reads only ``peel.zarr``.
"""
from __future__ import annotations

import numpy as np

from mmflow.calibrate.coherency import apparent_flux, source_vector_date
from mmflow.calibrate.dd_screen import screen_basis, sky_tangents_enu
from mmflow.calibrate.peel import PEEL, SKIP, SUBTRACT, peel, select_modes
from mmflow.calibrate.source_models import position_gains
from mmflow.io.run_stores import PEEL_MODES, peel_store
from mmflow.simulate.corrupt import gain_products
from mmflow.sky.sources import get_sources
from mmflow.workflow.baseline_cuts import check_baselines, solve_mask
from mmflow.workflow.blocks import read_block
from mmflow.workflow.chunking import TIME_CHUNK, chunk_rows, time_keys
from mmflow.workflow.peel_models import fitted_tables, peel_coherencies, peel_components
from mmflow.workflow.stages.base import Stage


def _prepare(ctx):
    vg = ctx.open("vis.zarr")
    nt, _, nf, npol = vg["vis"].shape
    n_ant = vg["antenna_enu"].shape[0]
    # with no baseline long enough every fit would be empty: refuse before any task
    check_baselines(ctx.telescope(), vg["pairs"][:], ctx.cfg.peel.min_baseline_lambda, "peel.min_baseline_lambda")
    names = _names(ctx.cfg.peel)
    # the models stage's fits replace the catalogue's point models when it is enabled: an input
    # whose producer's fingerprint then enters this stage's
    fitted = {}
    if ctx.producer("models.zarr") is not None:
        fitted = fitted_tables(ctx.open("models.zarr"), names)
    ctx.create(peel_store(nt, nf, len(names), n_ant, npol, TIME_CHUNK,
                          {"sources": names, "peeled": list(ctx.cfg.peel.peel),
                           "modelled": list(ctx.cfg.peel.model_sources), "fitted_models": fitted,
                           "modes": {n: i for i, n in enumerate(PEEL_MODES)}, "pols": vg.attrs["pols"]}))
    return [k for fi in range(nf) for k in time_keys(nt, freq=fi)]


def _names(p):
    """Every source the peel stage fits: the removed ones (``peel.sources``), then the modelled ones."""
    return list(p.sources) + list(p.model_sources)


def _task(ctx, key):
    p = ctx.cfg.peel
    fi = key.freq
    rows = slice(*chunk_rows(key, ctx.open("vis.zarr")["lst"].shape[0]))
    block = read_block(ctx, rows)
    tel = ctx.telescope()
    f = float(tel.freqs_hz[fi])
    lst = block.lst
    good = np.isfinite(lst)
    names = _names(p)
    coh = peel_coherencies(ctx, tel, fi, lst, block.pairs, names)
    epoch = float(ctx.vis_attrs()["epoch_jd"])
    flux, elev = apparent_flux(tel, f, np.where(good, lst, 0.0), get_sources(names), epoch)
    modes = select_modes(flux, elev, peelable=[n in p.peel for n in names],
                         peel_min_elevation_deg=p.peel_min_elevation_deg, peel_min_flux_jy=p.peel_min_flux_jy,
                         modelled=[n in p.model_sources for n in names])
    modes[:, ~good] = SKIP
    keep = solve_mask(tel, block.pairs, p.min_baseline_lambda, f)
    solint = 1 if p.solint_s is None else max(1, int(round(p.solint_s / float(ctx.vis_attrs()["integration_s"]))))
    basis = None
    if p.dd_model == "screen":  # the phase per unit refractive offset of each source, per integration
        vec = np.stack([source_vector_date(s, epoch) for s in get_sources(names)])
        basis = screen_basis(tel.layout.enu, f, sky_tangents_enu(tel, np.where(good, lst, 0.0), vec))
    kw = dict(dd_model=p.dd_model, screen_basis=basis, baseline_keep=keep, batch=p.batch, warm_start=p.warm_start,
              passes=p.passes, tol=p.tol, max_iter=p.max_iter, guard=p.guard, solint=solint)
    out = peel(block.vis[:, :, fi], block.weights[:, :, fi], coh, block.pairs, tel.n_ant, modes, **kw)
    h = np.ones(out.dd_gains.shape[:3], complex)  # (src, time, ant): subtracted sources at their positions
    if p.fit_positions:
        h = _fit_positions(ctx, tel, f, block, fi, out, coh, keep, good)
        coh = coh * gain_products(h[..., None], block.pairs)[..., 0]
        out = peel(block.vis[:, :, fi], block.weights[:, :, fi], coh, block.pairs, tel.n_ant, modes, **kw)
    sub = out.mode == SUBTRACT  # (src, time, pol): stored DD gains are the position gradient (1: catalogue)
    out.dd_gains = np.where(sub[:, :, None, :], h[..., None], out.dd_gains)
    g = ctx.open("peel.zarr", mode="r+")
    region = (rows, slice(fi, fi + 1))

    def per_time(x):  # (n_src, time, ...) -> (time, 1, n_src, ...)
        return np.moveaxis(x, 0, 1)[:, None]

    ctx.write(g, "dd_gains", region, per_time(out.dd_gains))
    for name in ("scale", "mode", "guard", "measured", "removed", "converged"):
        ctx.write(g, name, region, per_time(getattr(out, name)))
    peeled = out.mode == PEEL
    return {"peeled": int(peeled.sum()), "guard_fired": int(out.guard.sum()),
            "not_converged": int((peeled & ~out.converged).sum())}


def _fit_positions(ctx, tel, f, block, fi, out, coh, keep, good):
    """DD phase gradients (src, time, ant) of each subtracted source's fitted position per
    integration (:func:`mmflow.calibrate.source_models.position_gains`) on the peeled data with the
    source put back (mean of the polarisations; autos and short baselines unused); 1 elsewhere."""
    h = np.ones(out.dd_gains.shape[:3], complex)
    w = block.weights[:, :, fi].min(-1) * keep * (block.pairs[:, 0] != block.pairs[:, 1])
    epoch = float(ctx.vis_attrs()["epoch_jd"])
    for s, src in enumerate(get_sources(_names(ctx.cfg.peel))):
        sub = (out.mode[s] == SUBTRACT).any(-1) & good & (w.sum(1) > 0)  # a flagged integration: no fit
        if not sub.any():
            continue
        data = (out.residual[sub] + out.scale[s][sub][:, None, :] * coh[s][sub][..., None]).mean(-1)
        _, h[s, sub] = position_gains(tel, f, block.lst[sub], block.pairs, source_vector_date(src, epoch), data, w[sub])
    return h


def _apply(ctx, block):
    """Subtract every channel's peeled and subtracted sources from a block, in place (reads only
    ``peel.zarr``, never the configuration); the modelled sources stay."""
    for fi in range(block.vis.shape[2]):
        block.vis[:, :, fi] -= peel_components(ctx, block, fi, (PEEL, SUBTRACT))


STAGE = Stage("peel", ("peel", "beam"), ("vis.zarr", "gains.zarr", "models.zarr"), ("peel.zarr",), _prepare, _task, kind="solve",
               apply=_apply, enabled=lambda cfg: cfg.peel.enabled,
               counters=("peeled", "guard_fired", "not_converged"),
               description="peel (DD gains) or subtract bright sources per integration (applied on read)")
