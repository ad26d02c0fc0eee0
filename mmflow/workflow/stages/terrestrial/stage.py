"""The ``terrestrial`` stage (solve-then-apply, two phases): signals that do not move with the sky.

Paper section 5.4, on the calibrated and peeled data (the corrections of the stages before
it, :func:`read_block`):

1. tasks ``s{F}_t{K}`` sum each channel's time chunk's visibilities and weights per baseline with
   the phase centre at zenith (drift-scan data as stored); the sky smears into rings over > 24 h, a
   cross-talk pattern or a near-field emitter does not;
2. the driver adds the sums in a fixed order (:func:`ordered_tree_sum`), and fits
   ``terrestrial.components`` rank-1 patterns ``u_k`` to the average per channel and polarisation
   (:func:`mmflow.calibrate.terrestrial.fit_templates`); the templates are the K^2 Hermitian
   ``u_k u_l^H`` combinations (``u_k u_k^H`` alone for one component);
3. tasks ``a{F}_t{K}`` fit a real amplitude per template and integration on baselines longer than
   ``terrestrial.min_baseline_lambda`` (:func:`fit_amplitudes`) and report how much of the data
   each template sees, ``||B^H v_t|| / (||B|| ||v_t||)`` (:func:`projection_fraction`).

Both phases hold out the fitted ``peel.model_sources`` (:func:`mmflow.workflow.engine.peel_models.modelled_sources`):
the catalogued sky left in the data would otherwise leak into the templates and, integration by
integration, into their amplitudes.

Four correlations (the data hold xy, yx and the beam is an E-field beam:
:func:`~mmflow.workflow.engine.peel_models.four_correlation_jones`): a terrestrial signal's coherency over
the feeds is positive semi-definite, so its cross block lies in the span of the parallel hands'
patterns, ``xy = sum_kl a_kl u_kx u_ly^H`` (yx its Hermitian transpose); the phase-2 tasks also fit
the K^2 complex ``a_kl(t)`` per integration to the cross hands (:mod:`mmflow.calibrate.cross_hands`,
same baselines, the modelled sources held out there too).

The fit takes from the sky whatever of it lies along the templates. With ``terrestrial.amplitudes: auto``
the driver measures, after fitting the templates, the largest share of a source's map peak that the fit
would take at any declination, weighed by how well the array sees it
(:func:`mmflow.calibrate.terrestrial.sky_loss`, from the templates, the array and the beam alone); beyond
:data:`SKY_LOSS_LIMIT` (a small array whose templates are the residual sky's circumpolar rings) each
amplitude is held at its mean over the day, the stationary part, which the solve's m-filter drops with
m = 0 anyway. A last driver step averages the amplitudes (:func:`mean_amplitudes`).

``apply`` subtracts ``sum_k a_k(t) B_k`` (or the means) from a block where it is read (and ``sum_kl a_kl(t) T^kl``
from its cross hands where they are read). Every task reads and
corrects one channel (:func:`read_block`'s ``channels``): its memory does not grow with the run's
channels.
"""
from __future__ import annotations

import numpy as np

from mmflow.calibrate.cross_hands import cross_model, fit_cross, pattern_templates
from mmflow.calibrate.terrestrial import (fit_amplitudes, fit_templates, mean_amplitudes, projection_fraction,
                                          subtract_templates, template_basis, template_sky_loss)
from mmflow.io.calibration_stores import terrestrial_store
from mmflow.io.run_stores import STORES
from mmflow.workflow.engine.baseline_cuts import solve_mask
from mmflow.workflow.engine.blocks import read_block
from mmflow.workflow.engine.chunking import TIME_CHUNK, chunk_rows, time_keys
from mmflow.errors import InputError
from mmflow.workflow.engine.peel_models import four_correlation_jones, modelled_sources
from mmflow.workflow.engine.reduce import ordered_tree_sum
from mmflow.workflow.stages.terrestrial.cost import COST
from mmflow.workflow.stages.base import Stage

#: ``terrestrial.amplitudes: auto`` fits the amplitudes per integration where that takes at most this share of
#: a source's map peak at every declination, weighed by how well the array sees it
#: (:func:`mmflow.calibrate.terrestrial.sky_loss`; measured: 0.27 of an unmodelled circumpolar source lost on 18
#: stands within 20 m where the sky loss was 0.14-0.15; templates unrelated to the sky take ``K^2 / (2 n_bl)``,
#: 2 % there; the calibration demo's cross-talk and near-field emitter 0.0035)
SKY_LOSS_LIMIT = 0.05


def _prepare(ctx):
    vg = ctx.open(STORES.vis)
    nt, nbl, nf, npol = vg[STORES.vis.vis].shape
    ctx.create(terrestrial_store(len(time_keys(nt)), nt, nf, nbl, ctx.cfg.terrestrial.components,
                                 vg[STORES.vis.antenna_enu].shape[0], npol, TIME_CHUNK,
                                 cross=four_correlation_jones(ctx) is not None))
    return _keys(nt, nf, "s")


def _keys(nt, nf, phase):
    """One task per channel and time chunk: ``{phase}{F}_t{K}``."""
    return [k for fi in range(nf) for k in time_keys(nt, phase=phase, freq=fi)]


def _templates(ctx, fi, pairs):
    """The (K^2, bl, pol) templates of channel ``fi`` for ``pairs`` (:func:`template_basis` of its K patterns)."""
    return template_basis(ctx.read(STORES.terrestrial.patterns, (slice(fi, fi + 1),))[0], pairs)


def _task(ctx, key):
    k, fi = key.time, key.freq
    rows = slice(*chunk_rows(key, ctx.open(STORES.vis)[STORES.vis.lst].shape[0]))
    # phase 2: the cross hands too
    four = key.phase != "s" and STORES.terrestrial.cross_amplitudes in ctx.open(STORES.terrestrial)
    block = read_block(ctx, rows, channels=slice(fi, fi + 1), cross=four)  # its channel only
    if ctx.cfg.peel.enabled and ctx.cfg.peel.model_sources:
        par, cross = modelled_sources(ctx, block)
        block.vis -= par
        if cross is not None:
            block.cross -= cross
    vis = block.vis[:, :, 0]  # (time, bl, pol)
    g = ctx.open(STORES.terrestrial, mode="r+")
    w = np.where(np.isfinite(block.lst)[:, None, None], block.weights[:, :, 0], 0.0)
    region = (slice(k, k + 1), slice(fi, fi + 1))
    if key.phase == "s":  # phase 1: weighted sums
        v = np.where(w > 0, vis, 0)
        ctx.write(g, STORES.terrestrial.sum_vis, region, (w * v).sum(0)[None, None])
        ctx.write(g, STORES.terrestrial.sum_weight, region, w.sum(0)[None, None])
        return {}
    tel = ctx.telescope()  # phase 2: amplitudes per integration
    B = _templates(ctx, fi, block.pairs)
    keep = solve_mask(tel, block.pairs, ctx.cfg.terrestrial.min_baseline_lambda, float(tel.freqs_hz[fi]))
    amps = fit_amplitudes(vis, w, B, keep)
    seen = []
    for c in range(B.shape[0]):
        for p in range(B.shape[-1]):
            v = vis[:, keep, p].T
            if np.linalg.norm(v) > 0:
                seen.append(projection_fraction(B[c, keep, p][:, None], v))
    ctx.write(g, STORES.terrestrial.amplitudes, (rows, slice(fi, fi + 1)), amps[:, None])
    if four:
        wc = np.where(np.isfinite(block.lst)[:, None, None], block.cross_weights[:, :, 0], 0.0)
        wc = wc * (keep & (block.pairs[:, 0] != block.pairs[:, 1]))[:, None]
        patterns = ctx.read(STORES.terrestrial.patterns, (slice(fi, fi + 1),))[0]
        ca = fit_cross(np.where(wc > 0, block.cross[:, :, 0], 0), wc, pattern_templates(patterns, block.pairs))
        ctx.write(g, STORES.terrestrial.cross_amplitudes, (rows, slice(fi, fi + 1)), ca[:, None])
    return {"max_projection_fraction": float(max(seen, default=0.0))}


def _next_cycle(ctx, cycle):
    """After the sums: fit the templates and measure their sky loss (driver), then the amplitudes (tasks); then
    their means over the day (:func:`_finalize`)."""
    if cycle > 0:
        return None
    t = ctx.cfg.terrestrial
    g = ctx.open(STORES.terrestrial, mode="r+")
    n, nf = g[STORES.terrestrial.sum_vis].shape[:2]
    pairs = ctx.open(STORES.vis)[STORES.vis.pairs][:]
    patterns = np.zeros(g[STORES.terrestrial.patterns].shape, complex)
    loss = np.zeros(nf)
    for fi in range(nf):  # every cross baseline: the template is never extrapolated
        total = ordered_tree_sum([g[STORES.terrestrial.sum_vis][i, fi] for i in range(n)])  # (bl, pol)
        weight = ordered_tree_sum([g[STORES.terrestrial.sum_weight][i, fi] for i in range(n)])
        mean = np.where(weight > 0, total / np.where(weight > 0, weight, 1), 0)
        patterns[fi] = fit_templates(mean, weight, pairs, ctx.telescope().n_ant, t.components).patterns
        loss[fi] = _sky_loss(ctx, fi, pairs, weight, patterns[fi])
    ctx.write(g, STORES.terrestrial.patterns, (slice(None),), patterns)
    ctx.write(g, STORES.terrestrial.sky_loss, (slice(None),), loss)
    per = loss <= SKY_LOSS_LIMIT if t.amplitudes == "auto" else np.full(nf, t.amplitudes == "per_integration")
    ctx.write(g, STORES.terrestrial.per_integration, (slice(None),), per)
    return _keys(ctx.open(STORES.vis)[STORES.vis.lst].shape[0], nf, "a")


def _sky_loss(ctx, fi, pairs, weight, patterns):
    """The largest share of a source's map peak, over the declinations that rise (each weighed by how well the
    array sees it), that fitting channel ``fi``'s templates per integration would take, on the baselines the
    fit uses weighted by the day's summed weights (:func:`template_sky_loss`)."""
    tel = ctx.telescope()
    f = float(tel.freqs_hz[fi])
    used = solve_mask(tel, pairs, ctx.cfg.terrestrial.min_baseline_lambda, f) & (pairs[:, 0] != pairs[:, 1])
    return template_sky_loss(patterns, pairs, tel.layout.enu, f, weight, used, np.deg2rad(tel.layout.lat_deg),
                             tel.beam.power_enu)


def _finalize(ctx):
    """Each template's amplitude averaged over the day (what ``apply`` subtracts where the channel's
    ``per_integration`` is false); the summary states each channel's sky loss and choice."""
    g = ctx.open(STORES.terrestrial, mode="r+")
    h = STORES.terrestrial
    nf = g[h.patterns].shape[0]
    ctx.write(g, h.mean_amplitudes, (slice(None),), np.stack([mean_amplitudes(g[h.amplitudes][:, fi])
                                                              for fi in range(nf)]))
    if h.cross_amplitudes in g:
        ctx.write(g, h.mean_cross_amplitudes, (slice(None),),
                  np.stack([mean_amplitudes(g[h.cross_amplitudes][:, fi]) for fi in range(nf)]))
    per, loss = g[h.per_integration][:], g[h.sky_loss][:]
    out = {"sky_loss": [round(float(x), 4) for x in loss],
           "amplitudes": ["per integration" if p else "mean over the day" for p in per]}
    if ctx.cfg.terrestrial.amplitudes == "auto" and not per.all():
        out["log"] = (f"templates' amplitudes held at their means over the day on {int((~per).sum())} of {len(per)} "
                      f"channels: fitted per integration they would take up to {loss.max():.0%} of a source's map "
                      f"peak (limit {SKY_LOSS_LIMIT:.0%}); a flickering emitter's fluctuation stays in the data "
                      "(terrestrial.amplitudes=per_integration fits it anyway)")
    return out


def _apply(ctx, block):
    """Subtract ``sum_k a_k(t) B_k`` per channel from a block, in place (and ``sum_kl a_kl(t) T^kl`` from its
    cross hands where they are read); the amplitudes' means over the day where the channel's
    ``per_integration`` is false."""
    amps = ctx.read(STORES.terrestrial.amplitudes, (block.rows,))  # (time, freq, K, pol)
    per = ctx.read(STORES.terrestrial.per_integration)
    means = ctx.read(STORES.terrestrial.mean_amplitudes)  # (freq, K, pol)
    # the means on every integration of such a channel, also one the fit never saw (no data: its weight stays 0)
    amps = np.where(per[None, :, None, None], amps, means[None])
    if block.cross is not None and STORES.terrestrial.cross_amplitudes not in ctx.open(STORES.terrestrial):
        raise InputError(str(ctx.run.store(STORES.terrestrial)), "cross_amplitudes", "the terrestrial solutions "
                         "hold the parallel hands only, and this stage reads the cross hands too",
                         "rerun the terrestrial stage with an E-field beam on data holding xy, yx (--force)")
    for k, fi in block.channel_indices():
        block.vis[:, :, k] = subtract_templates(block.vis[:, :, k], _templates(ctx, fi, block.pairs), amps[:, fi])
        if block.cross is not None:
            ca = ctx.read(STORES.terrestrial.cross_amplitudes, (block.rows, slice(fi, fi + 1)))[:, 0]
            if not per[fi]:
                ca = np.broadcast_to(ctx.read(STORES.terrestrial.mean_cross_amplitudes)[fi], ca.shape)
            patterns = ctx.read(STORES.terrestrial.patterns, (slice(fi, fi + 1),))[0]
            block.cross[:, :, k] -= cross_model(ca, pattern_templates(patterns, block.pairs))


STAGE = Stage(
    "terrestrial",
    ("terrestrial", "beam", "peel.enabled", "peel.model_sources"),
    (STORES.vis, STORES.gains, STORES.peel),
    (STORES.terrestrial,),
    _prepare,
    _task,
    kind="solve",
    apply=_apply,
    next_cycle=_next_cycle,
    finalize=_finalize,
    enabled=lambda cfg: cfg.terrestrial.enabled,
    description="rank-1 templates of the zenith-phased average, fitted per integration and subtracted (or their "
                "means over the day)",
    cost=COST,
)
