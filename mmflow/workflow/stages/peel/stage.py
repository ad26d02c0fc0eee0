"""The ``peel`` stage (solve-then-apply): bright sources peeled or subtracted per integration.

Tasks ``f{F}_t{K}`` run over channels and time chunks of ``vis.zarr``. Each reads its
integrations calibrated (the corrections of the stages before it, :func:`read_block`), takes
the model coherency of every ``peel.sources`` source through the beam at the data's epoch
(:func:`mmflow.calibrate.coherency.source_coherencies`), chooses per integration whether a
source is peeled (``peel.peel``, above ``peel.peel_min_elevation_deg``), subtracted with a
fitted flux, or skipped (below the horizon) (:func:`mmflow.workflow.stages.peel.solve.peel_solve`, which
``mmflow bench calibrate`` times, in single precision unless ``peel.tol`` < 1e-5); the ``peel.model_sources``
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

Four correlations (the data hold xy, yx and the beam is an E-field beam:
:func:`~mmflow.workflow.engine.peel_models.four_correlation_jones`): every source's model is its four
correlations through the E-field beam, the parallel hands solved as above each against its own
feed's model, and the cross hands fitted after them, one complex coefficient ``c_s`` per source and
integration (:func:`~mmflow.workflow.stages.peel.solve.peel_cross`, :mod:`mmflow.calibrate.cross_hands`)::

    xy_ij -= sum_s c_s h_s,ix conj(h_s,jy) M^s_ij,xy,      yx_ij -= sum_s conj(c_s) h_s,iy conj(h_s,jx) M^s_ij,yx

over the peeled and subtracted sources (``c_s`` absorbs the feeds' relative phase, which neither the
parallel hands' DD gains nor ``calibrate`` fix), so full-Stokes maps lose the sources in Q, U and V
as in I. Each ``c_s`` is bounded (:func:`~mmflow.calibrate.cross_hands.fit_cross_bounded`): drawn towards
the sources' common coefficient where the data barely measure it, and set to it when ``|c_s|`` would
exceed three times that (counted in the summary's ``cross_refused``).

With the ``models`` stage enabled, the sources it fitted are modelled by their fitted Gaussian
components (``models.zarr``) instead of the catalogue's points, in the solve and in ``apply``
alike: the peel stage copies them into ``peel.zarr``'s attribute ``fitted_models``, so ``apply``
(run by every later reader) reads only ``peel.zarr``.
"""
from __future__ import annotations

import numpy as np

from mmflow.calibrate.peel import PEEL, SUBTRACT
from mmflow.io.calibration_stores import PEEL_MODES, peel_store
from mmflow.io.run_stores import STORES
from mmflow.workflow.engine.baseline_cuts import check_baselines
from mmflow.workflow.engine.blocks import read_block
from mmflow.workflow.engine.chunking import TIME_CHUNK, chunk_rows, time_keys
from mmflow.workflow.engine.peel_models import (FOUR, fitted_tables, four_correlation_jones, peel_coherencies,
                                                peel_components)
from mmflow.workflow.stages.peel.solve import peel_cross, peel_names, peel_solve, solve_dtype
from mmflow.workflow.stages.peel.cost import COST
from mmflow.workflow.stages.base import Stage


def _prepare(ctx):
    vg = ctx.open(STORES.vis)
    nt, _, nf, npol = vg[STORES.vis.vis].shape
    n_ant = vg[STORES.vis.antenna_enu].shape[0]
    # with no baseline long enough every fit would be empty: refuse before any task
    check_baselines(ctx.telescope(), vg[STORES.vis.pairs][:], ctx.cfg.peel.min_baseline_lambda,
                    "peel.min_baseline_lambda")
    names = peel_names(ctx.cfg.peel)
    # the models stage's fits replace the catalogue's point models when it is enabled: an input
    # whose producer's fingerprint then enters this stage's
    fitted = {}
    if ctx.producer(STORES.models) is not None:
        fitted = fitted_tables(ctx.open(STORES.models), names)
    four = four_correlation_jones(ctx) is not None
    attrs = {"sources": names, "peeled": list(ctx.cfg.peel.peel), "modelled": list(ctx.cfg.peel.model_sources),
             "fitted_models": fitted, "modes": {n: i for i, n in enumerate(PEEL_MODES)}, "pols": vg.attrs["pols"]}
    if four:
        attrs["correlations"] = FOUR
    ctx.create(peel_store(nt, nf, len(names), n_ant, npol, TIME_CHUNK, attrs, cross=four))
    return [k for fi in range(nf) for k in time_keys(nt, freq=fi)]


def _task(ctx, key):
    fi = key.freq
    rows = slice(*chunk_rows(key, ctx.open(STORES.vis)[STORES.vis.lst].shape[0]))
    jones = four_correlation_jones(ctx)  # four correlations: the cross hands too
    block = read_block(ctx, rows, channels=slice(fi, fi + 1), cross=jones is not None)  # its channel only
    tel = ctx.telescope()
    coh = peel_coherencies(ctx, tel, fi, block.lst, block.pairs, peel_names(ctx.cfg.peel),
                           solve_dtype(ctx.cfg.peel), jones=jones)
    attrs = ctx.vis_attrs()
    out = peel_solve(tel, fi, block.lst, block.pairs, block.vis[:, :, 0], block.weights[:, :, 0],
                     coh if jones is None else coh[..., :2], ctx.cfg.peel, float(attrs["epoch_jd"]),
                     float(attrs["integration_s"]))
    g = ctx.open(STORES.peel, mode="r+")
    region = (rows, slice(fi, fi + 1))
    refused = 0
    if jones is not None:
        c, unmeasured = peel_cross(tel, fi, block.lst, block.pairs, block.cross[:, :, 0],
                                   block.cross_weights[:, :, 0], coh, out, ctx.cfg.peel)
        ctx.write(g, STORES.peel.cross_scale, region, c[:, None])
        refused = int(unmeasured.sum())

    def per_time(x):  # (n_src, time, ...) -> (time, 1, n_src, ...)
        return np.moveaxis(x, 0, 1)[:, None]

    ctx.write(g, STORES.peel.dd_gains, region, per_time(out.dd_gains))
    p = STORES.peel
    for name in (p.scale, p.mode, p.guard, p.measured, p.removed, p.converged):  # the peel result's fields
        ctx.write(g, name, region, per_time(getattr(out, name)))
    peeled = out.mode == PEEL
    return {"peeled": int(peeled.sum()), "guard_fired": int(out.guard.sum()),
            "not_converged": int((peeled & ~out.converged).sum()), "cross_refused": refused}


def _apply(ctx, block):
    """Subtract every channel's peeled and subtracted sources from a block, in place, and from its cross
    hands where they are read (reads only ``peel.zarr`` and the beam); the modelled sources stay."""
    for k, fi in block.channel_indices():
        par, cross = peel_components(ctx, block, fi, (PEEL, SUBTRACT), cross=block.cross is not None)
        block.vis[:, :, k] -= par
        if cross is not None:
            block.cross[:, :, k] -= cross


STAGE = Stage(
    "peel",
    ("peel", "beam"),
    (STORES.vis, STORES.gains, STORES.models),
    (STORES.peel,),
    _prepare,
    _task,
    kind="solve",
    apply=_apply,
    enabled=lambda cfg: cfg.peel.enabled,
    counters=("peeled", "guard_fired", "not_converged", "cross_refused"),
    description="peel (DD gains) or subtract bright sources per integration (applied on read)",
    cost=COST,
)
