"""The ``calibrate`` stage (solve-then-apply): autocorrelation ripple, then Stefcal gains.

Tasks, fanned out over frequencies and solution intervals (independent of storage chunks):

* ``r{F}``: the ripple ratio ``r(t)`` of every antenna and polarisation of channel F from the
  autocorrelations (:func:`mmflow.calibrate.ripple.ripple_ratio`, paper section 3.2);
* ``g{F}_{K}``: Stefcal gains of channel F on interval K against the model
  ``calibrate.sources`` through the beam at the data's epoch (with the ``short_dipole`` E-field beam
  and data holding xx and yy, each feed's parallel hand through its own power beam ``|J_p|^2``:
  :func:`mmflow.telescope.jones.feed_telescopes`; a pyuvdata beam is its Stokes-I power beam for both)
  (:func:`mmflow.calibrate.screened_gains.solve_gains_screened`: the ``calibrate.screen_sources``
  refracted and scintillating per integration, the rest as catalogued; ``calibrate.measure_flux``
  measured rather than setting the flux scale, ``flux_factor``), on ripple-corrected data and on baselines
  longer than ``calibrate.min_baseline_lambda`` (``auto``: 15 lambda, lowered until every antenna keeps
  half of its baselines, :mod:`mmflow.workflow.engine.baseline_cuts`); outlier antennas are flagged all at
  once and the solution re-solved until none is left (:func:`mmflow.calibrate.stefcal.flag_outlier_antennas`),
  and a solution that flags more than ``calibrate.max_flagged_fraction`` of the antennas with data stops
  the run naming them (a model that does not describe the data, or that many bad antennas).

The default recipe solves an interval of ``calibrate.solint_s`` (1 h) over the whole data set against
the four bright sources and applies, at each integration, a local quadratic fit in time to the
intervals' solutions (``calibrate.smooth_intervals``, sigma 1.5 intervals), each weighted by
``1 / u``, ``u`` the fraction of its data's power the calibrated model leaves (``gains.zarr``
``unexplained``; intervals above ``calibrate.max_unexplained`` unused)
(:func:`mmflow.calibrate.gain_tables.smooth_gains_at`): a slow drift of the gains is followed, and
what the unmodelled sky moves in each hour's solution is averaged down (docs/calibration.md, "Peeling
with defaults on a day mmflow did not make"). With ``calibrate.solint_s`` null (the paper's recipe)
there is one interval per channel: the ``calibrate.track_min`` minutes where the sources are highest
(:func:`best_track`), applied to the whole data set. With ``calibrate.smooth_intervals`` null the
gains between the intervals' centres are interpolated linearly in amplitude and phase
(``calibrate.interpolate``,
:func:`mmflow.calibrate.gain_tables.gains_at`). ``apply`` corrects a block where it is read: autos
by ``r_i``, cross correlations by ``sqrt(r_i r_j)`` and ``1 / (g_i conj(g_j))``; flagged antennas get weight 0,
and so do the autocorrelations with ``calibrate.flag_autos`` (the default): after calibration
they hold the receiver power times the residual gain error (a 1e-3 error in a 2e5 Jy receiver
power is 200 Jy, more than the faint sky), the ripple correction has replaced them by their own
45-min smooth, and peeling subtracts the bright sources' per-integration (scintillating) flux
from that smooth; imaged, they left ~110 K of large-scale error in the calibration demo's map
(docs/calibration.md). ``vis.zarr`` is never rewritten.
"""
from __future__ import annotations

import numpy as np

from mmflow.calibrate.baselines import antennas_with_data, baseline_lengths
from mmflow.calibrate.coherency import apparent_flux, source_coherencies, source_vector_date
from mmflow.calibrate.gain_tables import gains_at, interval_weights, smooth_gains_at
from mmflow.calibrate.ripple import apply_ripple, ripple_ratio
from mmflow.calibrate.dd_screen import screen_basis, sky_tangents_enu
from mmflow.calibrate.screened_gains import solve_gains_screened
from mmflow.calibrate.gain_apply import apply_gains, apply_gains_autos
from mmflow.calibrate.stefcal import best_track
from mmflow.errors import InputError
from mmflow.conventions import CROSS_FEEDS
from mmflow.io.calibration_stores import gains_store
from mmflow.io.run_stores import STORES
from mmflow.sky.sources import get_sources
from mmflow.telescope.jones import feed_telescopes
from mmflow.workflow.engine.baseline_cuts import check_baselines, resolved_cuts, solve_mask
from mmflow.workflow.engine.blocks import read_block
from mmflow.workflow.stages.calibrate.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey


def _epoch(ctx):
    return float(ctx.vis_attrs()["epoch_jd"])


def _intervals(ctx, tel, lst, integration_s):
    """``(solve_rows, apply_rows)`` (n_interval, 2) from ``calibrate.solint_s`` or the best track."""
    c, n = ctx.cfg.calibrate, len(lst)
    if c.solint_s is not None:
        step = max(1, int(round(c.solint_s / integration_s)))
        edges = np.array([(t0, min(n, t0 + step)) for t0 in range(0, n, step)], np.int64)
        return edges, edges
    good = np.isfinite(lst)
    flux, _ = apparent_flux(tel, float(tel.freqs_hz[0]), np.where(good, lst, 0.0), get_sources(c.sources),
                            _epoch(ctx))
    track = best_track(flux, max(1, int(round(c.track_min * 60 / integration_s))), good.astype(float))
    return np.array([[track.start, track.stop]], np.int64), np.array([[0, n]], np.int64)


def _prepare(ctx):
    vg = ctx.open(STORES.vis)
    nt, _, nf, npol = vg[STORES.vis.vis].shape
    lst = vg[STORES.vis.lst][:]
    tel = ctx.telescope()
    if ctx.cfg.calibrate.ripple and not np.isfinite(vg[STORES.vis.autos][:]).any():
        raise InputError(str(ctx.run.store(STORES.vis)), STORES.vis.autos, "no autocorrelations: the ripple correction "
                         "needs them", "ingest autocorrelations (telescope.include_autos), or set "
                         "calibrate.ripple=false")
    pairs = vg[STORES.vis.pairs][:]
    check_baselines(tel, pairs, ctx.cfg.calibrate.min_baseline_lambda, "calibrate.min_baseline_lambda")
    solve, apply = _intervals(ctx, tel, lst, vg.attrs["integration_s"])
    ctx.create(
        gains_store(
            len(solve),
            nf,
            tel.n_ant,
            npol,
            nt,
            solve,
            apply,
            {
                "sources": list(ctx.cfg.calibrate.sources),
                "pols": vg.attrs["pols"],
                "ripple": bool(ctx.cfg.calibrate.ripple),
                "interpolate": bool(ctx.cfg.calibrate.interpolate),
                **_smoothing(ctx.cfg.calibrate, vg.attrs["integration_s"]),
                "flag_autos": bool(ctx.cfg.calibrate.flag_autos),
                "min_baseline_lambda": resolved_cuts(tel, pairs, ctx.cfg.calibrate.min_baseline_lambda),
            },
            n_src=len(ctx.cfg.calibrate.sources),
        )
    )
    keys = [TaskKey(phase="r", freq=fi) for fi in range(nf)] if ctx.cfg.calibrate.ripple else []
    return keys + [TaskKey(phase="g", freq=fi, interval=k) for fi in range(nf) for k in range(len(solve))]


def _smoothing(c, integration_s):
    """The gains store's attributes of the smoothing of interval solutions (none without it)."""
    if c.solint_s is None or c.smooth_intervals is None:
        return {}
    step = max(1, int(round(c.solint_s / integration_s)))  # integrations per interval, as in _intervals
    return {"smooth_rows": c.smooth_intervals * step, "max_unexplained": c.max_unexplained,
            "smooth_degree": c.smooth_degree}


_RIPPLE = {}  # (run, channel, smoothing, configuration) -> ratio: one computation per worker process


def _ratio(ctx, fi):
    """Ripple ratio ``(time, antenna, pol)`` of channel ``fi`` from the autocorrelations."""
    key = (str(ctx.run_path), fi, ctx.cfg.calibrate.ripple_smooth_min, ctx.config_json)
    if key not in _RIPPLE:
        autos = ctx.read(STORES.vis.autos, (slice(None), slice(None), slice(fi, fi + 1)))[:, :, 0]
        finite = np.isfinite(autos)
        ratio, _ = ripple_ratio(np.where(finite, autos, 0.0), finite.astype(float),
                                ctx.open(STORES.vis).attrs["integration_s"], key[2] * 60.0)
        if len(_RIPPLE) >= 4:
            _RIPPLE.clear()
        _RIPPLE[key] = ratio
    return _RIPPLE[key]


def _task(ctx, key):
    g = ctx.open(STORES.gains, mode="r+")
    if key.phase == "r":
        fi = key.freq
        ctx.write(g, STORES.gains.ripple, (slice(None), slice(fi, fi + 1)), _ratio(ctx, fi)[:, None])
        return {"ripple_channels": 1}

    c = ctx.cfg.calibrate
    fi, k = key.freq, key.interval
    t0, t1 = (int(x) for x in g[STORES.gains.solve_rows][k])
    block = read_block(ctx, slice(t0, t1), channels=slice(fi, fi + 1))  # its channel only
    tel = ctx.telescope()
    f = float(tel.freqs_hz[fi])
    good = np.isfinite(block.lst)
    vis, w = block.vis[good, :, 0], block.weights[good, :, 0]
    if c.ripple:
        vis, w = apply_ripple(vis, w, block.pairs, _ratio(ctx, fi)[t0:t1][good])
    lst, sources = block.lst[good], get_sources(c.sources)
    epoch = _epoch(ctx)  # once: each call opens vis.zarr's attributes
    # a Jones beam and data holding xx and yy: each feed's parallel hand through its own power beam
    feeds = feed_telescopes(tel) if list(ctx.vis_attrs()["pols"]) == ["xx", "yy"] else None
    if feeds is None:
        coh = source_coherencies(tel, f, lst, sources, epoch, block.pairs)
    else:  # each feed's models filled in place (a stack of the two would hold them twice at its peak)
        coh = np.empty((len(sources), len(lst), len(block.pairs), len(feeds)), np.complex128)
        for p, t in enumerate(feeds):
            source_coherencies(t, f, lst, sources, epoch, block.pairs, out=coh[..., p])
    keep = solve_mask(tel, block.pairs, c.min_baseline_lambda, f)
    screened = np.array([name in c.screen_sources for name in c.sources], bool)
    vec = np.stack([source_vector_date(s, epoch) for s in sources])
    basis = screen_basis(tel.layout.enu, f, sky_tangents_enu(tel, lst, vec))
    reference = screened & np.array([name not in c.measure_flux for name in c.sources], bool)
    out = solve_gains_screened(vis, coh, w, block.pairs, tel.n_ant, basis, screened, reference=reference,
                               rounds=c.screen_rounds, baseline_keep=keep, tol=c.tol, max_iter=c.max_iter,
                               damping=c.damping, outlier_sigma=c.outlier_sigma,
                               baseline_lengths=baseline_lengths(block.pairs, tel.layout.enu, f))
    sol = out.solution
    has_data = antennas_with_data(w, block.pairs, tel.n_ant, keep)
    _stop_if_too_many_flagged(ctx, sol, has_data, f, (t0, t1), c)
    region = (slice(k, k + 1), slice(fi, fi + 1))
    ctx.write(g, STORES.gains.gains, region, np.where(sol.flags, 0, np.nan_to_num(sol.gains))[:, None])  # flagged: 0
    ctx.write(g, STORES.gains.flags, region, sol.flags[:, None])
    ctx.write(g, STORES.gains.chi2, region, np.nan_to_num(sol.chi2[:, None]))
    ctx.write(g, STORES.gains.unexplained, region, out.unexplained[None, None])
    ctx.write(g, STORES.gains.iterations, region, sol.iterations[:, None].astype(np.int32))
    ctx.write(g, STORES.gains.converged, region, sol.converged[:, None])
    ctx.write(g, STORES.gains.flux_factor, region, np.nan_to_num(out.flux, nan=0.0)[None, None])  # 0: never fitted
    return {"solutions": int(sol.converged.size), "not_converged": int((~sol.converged).sum()),
            "flagged_antennas": int((sol.flags[0] & has_data).any(axis=-1).sum()),
            "antennas_without_data": int((~has_data).all(axis=-1).sum()),
            "screened_integrations": int(np.isfinite(out.offsets[screened, ..., 0]).sum())}


def _stop_if_too_many_flagged(ctx, sol, has_data, f, rows, c):
    """Refuse a solution that flags more than ``calibrate.max_flagged_fraction`` of the antennas with
    data: most often a sky model which does not describe the data on the baselines used (missing bright
    sources, a wrong beam, a cut that keeps the diffuse sky), else that many bad antennas (the search
    finds up to about a third of the array holding noise, :mod:`mmflow.calibrate.outliers`); the later
    stages would fail on the coverage it leaves with a misleading message."""
    flagged = (sol.flags[0] & has_data).any(axis=-1)
    n_data = int(has_data.any(axis=-1).sum())
    if n_data == 0 or flagged.sum() <= c.max_flagged_fraction * n_data:
        return
    names = ctx.telescope().layout.names
    chi2 = sol.chi2[0]
    ok = ~sol.flags[0] & has_data
    med_ok = float(np.median(chi2[ok])) if ok.any() else float("nan")
    listed = ", ".join(str(names[a]) for a in np.flatnonzero(flagged)[:20])
    more = f" and {int(flagged.sum()) - 20} more" if flagged.sum() > 20 else ""
    raise InputError(str(ctx.run.store(STORES.gains)), "calibrate",
                     f"the gain solution at {f / 1e6:.3f} MHz (integrations {rows[0]}-{rows[1] - 1}) flagged "
                     f"{int(flagged.sum())} of the {n_data} antennas with data ({listed}{more}) as outliers or "
                     f"unconverged, more than calibrate.max_flagged_fraction={c.max_flagged_fraction:g} (the "
                     f"others' residual chi2 median {med_ok:.3g}): the sky model calibrate.sources="
                     f"{list(c.sources)} does not describe the data on the baselines used, or that many "
                     "antennas are bad",
                     "add the bright sources the track sees to calibrate.sources, set calibrate.min_baseline_lambda"
                     "=auto (or raise it past the diffuse sky's baselines), check the beam; or, if those antennas are "
                     "truly bad, flag them in the input or raise calibrate.max_flagged_fraction")


def _apply(ctx, block):
    """Ripple and gains of every channel on a block (time, baseline, freq, pol), in place, and on
    its autocorrelation powers (the ``mmodes`` stage's radiometer noise: in raw correlator units
    they would weigh each baseline by ``|g_i g_j|^2``).

    Reads only ``gains.zarr`` (never the configuration: the reading stage's fingerprint covers
    the store)."""
    gains = ctx.read(STORES.gains.gains)  # (interval, freq, antenna, pol): small
    flags = ctx.read(STORES.gains.flags)
    apply_rows, solve_rows = ctx.read(STORES.gains.apply_rows), ctx.read(STORES.gains.solve_rows)
    attrs = ctx.open(STORES.gains).attrs
    interpolate = bool(attrs.get("interpolate", False))
    smooth = attrs.get("smooth_rows")
    if smooth is not None:
        u = ctx.read(STORES.gains.unexplained)  # (interval, freq, pol)
        trust = interval_weights(u, attrs["max_unexplained"])
    rows = np.arange(block.rows.start, block.rows.stop)
    ratio = ctx.read(STORES.gains.ripple, (block.rows,)) if ctx.open(STORES.gains).attrs["ripple"] else None
    for k, fi in block.channel_indices():
        v, w, autos = block.vis[:, :, k], block.weights[:, :, k], block.autos[:, :, k]  # views: in place
        if ratio is not None:
            apply_ripple(v, w, block.pairs, ratio[:, fi], out=(v, w))
            autos = apply_gains_autos(autos, np.sqrt(ratio[:, fi]))
        if smooth is None:
            g, fl = gains_at(rows, gains[:, fi], flags[:, fi], apply_rows, solve_rows, interpolate)
        else:
            g, fl = smooth_gains_at(rows, gains[:, fi], flags[:, fi], solve_rows,
                                    np.broadcast_to(trust[:, fi, None, :], gains[:, fi].shape), smooth,
                                    attrs["smooth_degree"])
        apply_gains(v, w, block.pairs, g, fl, out=(v, w))
        block.autos[:, :, k] = apply_gains_autos(autos, g, fl)  # the radiometer noise of the corrected data
        if block.cross is not None:  # xy, yx: feed p of antenna i, feed q of antenna j
            cv, cw = block.cross[:, :, k], block.cross_weights[:, :, k]
            if ratio is not None:
                apply_ripple(cv, cw, block.pairs, ratio[:, fi], feeds=CROSS_FEEDS, out=(cv, cw))
            apply_gains(cv, cw, block.pairs, g, fl, feeds=CROSS_FEEDS, out=(cv, cw))
    if ctx.open(STORES.gains).attrs.get("flag_autos", False):
        autos = block.pairs[:, 0] == block.pairs[:, 1]
        block.weights[:, autos] = 0.0
        if block.cross is not None:
            block.cross_weights[:, autos] = 0.0


STAGE = Stage("calibrate", ("calibrate", "beam"), (STORES.vis,), (STORES.gains,), _prepare, _task, kind="solve",
               apply=_apply, enabled=lambda cfg: cfg.calibrate.enabled,
               counters=("not_converged", "flagged_antennas", "antennas_without_data", "screened_integrations"),
               description="autocorrelation ripple + Stefcal gains per solution interval (applied on read)", cost=COST)
