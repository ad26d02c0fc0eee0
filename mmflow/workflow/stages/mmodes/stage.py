"""The ``mmodes`` stage: corner turn (time -> baseline), corrections on read, m-modes.

Each task reads every integration of one baseline chunk from ``vis.zarr`` (whole chunks,
checked against the data stage's records), applies the corrections of the enabled
solve-then-apply stages (gains, peeled sources, terrestrial templates: never written back),
bins onto sidereal bins and calls :func:`mmflow.mmode.gapfill.chunk_mmodes`: least-squares
m-modes of each data split within each baseline's band limit (flagged time is not zero),
thermal noise from the radiometer equation or from the fit's residual, and per-baseline
coverage (``docs/mmodes.md``). It writes ``mmodes.zarr``.

Time-subset splits (``day<k>``, ``day``, ``night``; :mod:`mmflow.mmode.splits`) are binned from
their own integrations and fitted the same way; their masks are computed once per process from
``vis.zarr``'s ``lst`` and ``time_jd``, and the prepare refuses splits the data cannot make
(:func:`mmflow.mmode.splits.split_problems`) before any task; each task refuses a time split
whose unflagged samples miss ``mmode.min_coverage`` of the bins (a flagged day). Every task
counts each split's unflagged samples per frequency and baseline (``n_samples``): the jackknives'
shares ``f_k`` (:func:`mmflow.workflow.engine.geometry.split_fractions`).

With ``mmode.prior_run`` the fit of every chunk with flagged time takes as its prior the
m-modes of an earlier run's map (:func:`mmflow.mmode.gapfill.prior_mmodes` of that run's
``alm.zarr``, :mod:`mmflow.workflow.engine.prior_run`): what a baseline's gaps leave unmeasured comes
from the map (what the array saw of that sky at other times and on other baselines), not 0.
"""
from __future__ import annotations

import hashlib
import threading

import numpy as np

from mmflow.conventions import is_full_stokes
from mmflow.errors import CoverageError, InputError
from mmflow.conventions import CROSS_FEEDS
from mmflow.io.polarization import stokes_i, stokes_i_variance
from mmflow.io.run_stores import STORES, mmodes_store
from mmflow.mmode.gapfill import chunk_mmodes, prior_mmodes, refit_prior_m0
from mmflow.mmode.noise import radiometer_variance
from mmflow.mmode.polarised import CORRELATIONS
from mmflow.mmode.splits import day_index, is_time_split, split_kind, split_masks, split_problems, \
    sun_elevation_deg
from mmflow.mmode.transform import bin_coverage, sidereal_bins, split_bins
from mmflow.workflow.engine.blocks import read_block
from mmflow.workflow.engine.geometry import fit_band, fit_bins, mmax_of, n_bins_of
from mmflow.workflow.engine.prior_run import check_prior_run, effective_prior, prior_files, read_prior_alm
from mmflow.workflow.stages.mmodes.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey


def _prepare(ctx):
    cfg = ctx.cfg
    vis = ctx.open(STORES.vis)
    nt, nbl, nf = vis[STORES.vis.vis].shape[:3]
    mmax, n_bins = mmax_of(cfg), n_bins_of(cfg, vis.attrs["integration_s"])
    splits = list(cfg.mmode.splits)
    prior = effective_prior(cfg.mmode, ctx.run.path)
    if prior is not None:  # channels and epoch of ingested data are known only now
        check_prior_run(prior, cfg.mmode.lmax, mmax, ctx.run.path, vis[STORES.vis.freqs_hz][:],
                        float(vis.attrs["epoch_jd"]))
    _check_day(ctx, vis[STORES.vis.lst][:], n_bins, cfg.mmode.min_coverage)
    attrs = {"mmax": mmax, "n_bins": n_bins, "splits": splits}
    if any(is_time_split(s) for s in splits):
        attrs.update(_check_time_splits(ctx, vis, splits, n_bins))
    n_corr = 0
    if is_full_stokes(cfg.imaging.stokes):
        _check_correlations(ctx, vis)
        n_corr = len(CORRELATIONS)
    ctx.create(mmodes_store(len(splits), nf, mmax, nbl, vis[STORES.vis.vis].chunks[1], attrs, n_corr))
    return [TaskKey(bl_chunk=i) for i in range(-(-nbl // vis[STORES.vis.vis].chunks[1]))]


def _check_correlations(ctx, vis):
    """Full Stokes needs both parallel hands and both cross hands in ``vis.zarr``."""
    pols, cross = list(vis.attrs.get("pols", [])), list(vis.attrs.get("cross_pols") or [])
    if len(pols) != 2 or len(cross) != 2:
        raise InputError(str(ctx.run.store(STORES.vis)), "cross_pols",
                         f"polarisations {pols} and cross hands {cross}: imaging.stokes [I, Q, U, V] needs the four "
                         "correlations xx, yy, xy, yx",
                         "ingest files that hold XX, YY, XY and YX (input.cross_hands true), or set imaging.stokes=[I]")


def _time_splits(ctx, vis, splits):
    """``(lst, days, {split: integration mask})`` over every integration of ``vis.zarr`` (NaN LSTs in no
    split), the Sun's elevation computed only for ``day`` / ``night``; cached per process for the
    data's times (every task of a run needs the same masks)."""
    lst, times = vis[STORES.vis.lst][:], vis[STORES.vis.time_jd][:]
    a = vis.attrs
    sun = any(split_kind(s)[0] == "sun" for s in splits)
    key = (hashlib.sha1(lst.tobytes() + times.tobytes()).hexdigest(), tuple(splits),
           (a["lat_deg"], a["lon_deg"], a.get("height_m", 0.0)) if sun else None)
    with _MASKS_LOCK:  # tasks of one process run in threads: one computes, the others wait for it
        entry = _MASKS.get(key)
        if entry is None:
            good = np.isfinite(lst)
            days = np.full(len(lst), -1)
            days[good] = day_index(lst[good], times[good])
            elev = sun_elevation_deg(times, a["lat_deg"], a["lon_deg"], a.get("height_m", 0.0)) if sun else None
            entry = (lst, days, elev, {s: m & good for s, m in split_masks(splits, days, elev).items()})
            _MASKS.clear()
            _MASKS[key] = entry
    return entry


_MASKS = {}  # one entry: the masks of the latest data and splits
_MASKS_LOCK = threading.Lock()


def _check_time_splits(ctx, vis, splits, n_bins):
    """Refuse time-subset splits the data cannot make (:func:`mmflow.mmode.splits.split_problems`);
    return the attributes of the days: how many sidereal days the data span and which hold data."""
    lst, days, elev, _ = _time_splits(ctx, vis, splits)
    good = np.isfinite(lst)
    problems = split_problems(splits, lst[good], days[good], None if elev is None else elev[good], n_bins,
                              ctx.cfg.mmode.min_coverage)
    if problems:
        name, problem, fix = problems[0]
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise InputError(str(ctx.run.store(STORES.vis)), "mmode.splits", f"'{name}': {problem}{more}", fix)
    present = np.unique(days[days >= 0])
    return {"n_days": int(present.max()) + 1 if present.size else 0, "days": [int(d) for d in present]}


def _task(ctx, key):
    vg = ctx.open(STORES.vis)
    nbl = vg[STORES.vis.vis].shape[1]
    ch = vg[STORES.vis.vis].chunks[1]
    i = key.bl_chunk
    cols = slice(i * ch, min(nbl, (i + 1) * ch))
    full_stokes = STORES.mmodes.mmodes_corr in ctx.open(STORES.mmodes)
    block = read_block(ctx, slice(None), cols, cross=full_stokes)  # all integrations, corrected
    good_t = np.isfinite(block.lst)
    g = ctx.open(STORES.mmodes, mode="r+")
    mmax, n_bins, splits = g.attrs["mmax"], g.attrs["n_bins"], g.attrs["splits"]
    bin_splits = [s for s in splits if not is_time_split(s)]
    masks = {s: m[good_t] for s, m in _time_splits(ctx, vg, splits)[3].items()} if len(bin_splits) < len(splits) \
        else {}
    fit = _SplitFit(ctx, block.lst[good_t], masks, splits, n_bins, mmax)
    # the bins of the smallest split bound the fit: half of them for even / odd
    n_fit = fit_bins(splits, n_bins)
    info = _stokes_i_mmodes(ctx, vg, g, block, good_t, cols, n_fit, fit)  # written; its arrays freed on return
    if full_stokes:
        corr, inv_corr = _correlation_mmodes(ctx, vg, block, good_t, n_fit, mmax, fit)
        ctx.write(g, STORES.mmodes.mmodes_corr, (slice(None),) * 5 + (cols,), corr)
        ctx.write(g, STORES.mmodes.inv_var_corr, (slice(None), slice(None), cols), inv_corr)
    return info


def _stokes_i_mmodes(ctx, vg, g, block, good_t, cols, n_fit, fit):
    """Fit and write the Stokes-I m-modes ``(split, freq, m, pm, baseline)`` of one baseline chunk, their inverse
    variances and unflagged samples; return the task's information (noise, coverage, iterations)."""
    vis, w = stokes_i(block.vis[good_t], block.weights[good_t])
    per_pol, noise = _radiometer_sigma2(ctx, vg, block.autos[good_t], block.pairs,
                                        [(p, p) for p in range(block.vis.shape[-1])])
    sigma2 = None if per_pol is None else stokes_i_variance(np.stack(per_pol, axis=-1))
    tel, freqs = ctx.telescope(), vg[STORES.vis.freqs_hz][:]
    nf, nbl = vis.shape[2], vis.shape[1]
    out = np.zeros((len(fit.splits), nf, fit.mmax + 1, 2, nbl), np.complex128)
    inv_var = np.zeros((nf, nbl))
    n_samples = np.zeros((len(fit.splits), nf, nbl), np.int64)
    info = {"baselines": int(nbl), "noise": noise, "dropped_low_coverage": 0,
            "downweighted_low_coverage": 0, "baselines_without_data": 0, "max_cg_iterations": 0,
            "fits_with_prior": 0}
    for fi in range(nf):
        band = fit_band(tel, freqs[fi], n_fit, block.pairs)
        model = _PriorModel(ctx, tel, freqs[fi], fi, np.arange(cols.start, cols.stop))
        inv_var[fi], coverage, n_samples[:, fi], n_prior = fit(vis[:, :, fi], w[:, :, fi], band,
                                                               None if sigma2 is None else sigma2[fi], out[:, fi],
                                                               model.prior)
        info["fits_with_prior"] += n_prior
        info["max_cg_iterations"] = max(info["max_cg_iterations"], fit.max_iterations)
        info["dropped_low_coverage"] += coverage.n_dropped  # the full data's coverage
        info["downweighted_low_coverage"] += coverage.n_downweighted
        info["baselines_without_data"] += coverage.n_empty
    ctx.write(g, STORES.mmodes.mmodes, (slice(None), slice(None), slice(None), slice(None), cols), out)
    ctx.write(g, STORES.mmodes.inv_var, (slice(None), cols), inv_var)
    ctx.write(g, STORES.mmodes.n_samples, (slice(None), slice(None), cols), n_samples)
    return info


def _correlation_mmodes(ctx, vg, block, good_t, n_fit, mmax, fit):
    """m-modes ``(split, freq, m, pm, correlation, baseline)`` and their inverse variances ``(freq, correlation,
    baseline)`` of xx, yy, xy, yx (full Stokes), each fitted as Stokes I is (every data split, no prior run)
    with each correlation's own radiometer noise ``<V_ii,p> <V_jj,q> / (dnu tau)``.

    Where the radiometer equation is not used (``mmode.noise: data``, or ``auto`` with an antenna of the chunk
    without autocorrelations) the parallel hands' per-sample variances come from their fits' residuals, and
    the cross hands take the radiometer equation's relation to them, ``sigma^2_xy sigma^2_yx = sigma^2_xx
    sigma^2_yy``, as ``sigma^2_xy = sigma^2_yx = sqrt(sigma^2_xx sigma^2_yy)`` per sample (their own flags and
    coverage still set their m-modes' variances; a baseline with no xx or no yy data has none): a cross hand's own
    residual follows its modelling error where the noise is small: on a noise-free four-correlation day
    (``tests/independent_day.py``, no autocorrelations) the cross hands outweighed the parallel hands 137
    times (median; 1.01 with radiometer noise in the file) and the full-Stokes I came out at 0.32-0.49 of the
    noisy file's (0.97-0.99 with the relation; the Stokes-I path 0.98-0.995)."""
    hands = [(block.vis, block.weights, p) for p in range(block.vis.shape[-1])]  # xx, yy, then xy, yx
    hands += [(block.cross, block.cross_weights, p) for p in range(block.cross.shape[-1])]
    feeds = [(0, 0), (1, 1)] + list(zip(*CROSS_FEEDS))
    per_corr, _ = _radiometer_sigma2(ctx, vg, block.autos[good_t], block.pairs, feeds)
    tel, freqs = ctx.telescope(), vg[STORES.vis.freqs_hz][:]
    nf, nbl = block.vis.shape[2], block.vis.shape[1]
    out = np.zeros((len(fit.splits), nf, mmax + 1, 2, len(feeds), nbl), np.complex128)
    inv_var = np.zeros((nf, len(feeds), nbl))
    for fi in range(nf):
        band = fit_band(tel, freqs[fi], n_fit, block.pairs)
        parallel = []  # the parallel hands' per-sample variances (bl,), where estimated from their residuals
        for c, (v, w, p) in enumerate(hands):  # one correlation's integrations at a time (no copy of all four)
            sigma2 = per_corr[c][fi] if per_corr is not None else (np.sqrt(parallel[0] * parallel[1]) if c >= 2
                                                                   else None)
            inv_var[fi, c] = fit(v[good_t, :, fi, p], w[good_t, :, fi, p], band, sigma2, out[:, fi, :, :, c])[0]
            if c < 2:
                parallel.append(fit.sigma2)
    return out, inv_var


class _SplitFit:
    """The m-modes of every data split of one baseline chunk at one frequency: the bin-parity splits
    (``full``, ``even``, ``odd``) from one binning, each time split from its own integrations
    (:func:`mmflow.mmode.gapfill.chunk_mmodes`); what Stokes I and each correlation share.

    Calling it with ``(vis, weights)`` ``(time, bl)``, the band limits, the per-sample variance (or
    None), the output ``(split, mmax + 1, 2, bl)`` and optionally ``prior(binned, weights, offset)``
    fills the output and returns ``(inverse variances (bl), coverage, n_samples (split, bl), fits with a prior)``,
    the first two of the full data (the fits' own m-modes are not kept: a task fits up to five times, Stokes I
    and four correlations, into outputs it holds); a time split without ``mmode.min_coverage`` of the bins is
    refused.
    """

    def __init__(self, ctx, lst, masks, splits, n_bins, mmax):
        self.ctx, self.lst, self.masks, self.splits, self.n_bins, self.mmax = ctx, lst, masks, splits, n_bins, mmax
        self.bin_splits = [s for s in splits if not is_time_split(s)]
        self.src = str(ctx.run.store(STORES.vis))
        self.max_iterations, self.sigma2 = 0, None

    def __call__(self, vis, weights, band, sigma2, out, prior=None):
        cfg, splits = self.ctx.cfg, self.splits
        n_samples = np.zeros((len(splits), vis.shape[1]), np.int64)
        full, n_prior = None, 0
        for names, sel in [(self.bin_splits, slice(None))] + [([s], m) for s, m in self.masks.items()]:
            binned, wsum, offset = sidereal_bins(self.lst[sel], vis[sel], (weights[sel] > 0).astype(float),
                                                 self.n_bins, 0.0, source=self.src)
            if names is not self.bin_splits:  # a flagged day of a time split (the full data: _finalize)
                _check_split_coverage(wsum, cfg.mmode.min_coverage, self.src, self.n_bins, names[0])
            rows = [splits.index(s) for s in names]
            n_samples[rows] = [_count(wsum, s) for s in names]
            model = None if prior is None else prior(binned, wsum, offset)
            n_prior += model is not None
            res = chunk_mmodes(binned, wsum, self.mmax, offset, band, names if names is self.bin_splits else ["full"],
                               sigma2, cfg.mmode.min_coverage, cfg.mmode.coverage_policy, prior=model)
            out[rows] = res.mmodes
            self.max_iterations = max([self.max_iterations] + [int(np.max(f.iterations)) for f in res.fits])
            if names is self.bin_splits:
                full = (res.inv_var, res.coverage)
                self.sigma2 = res.sigma2  # the per-sample variance the full data's fit used (given or estimated)
        return (*full, n_samples, n_prior)


def _count(bin_weight, split):
    """Unflagged samples per baseline of ``split`` from the summed 0/1 weights of the bins it was
    fitted from: all bins, or the even / odd ones for a bin parity (the rows of
    :func:`mmflow.mmode.transform.split_bins`)."""
    rows = slice(None) if is_time_split(split) else split_bins(len(bin_weight), None, [split])[0][0]
    return np.rint(bin_weight[rows].sum(axis=0)).astype(np.int64)


class _PriorModel:
    """The earlier run's model m-modes ``B_m a_m`` for the chunk's baselines (``mmode.prior_run``), computed
    at most once per chunk and frequency, and fitted to each split's bins.

    :meth:`prior` gives the model with its ``m = 0`` fitted to the data
    (:func:`mmflow.mmode.gapfill.refit_prior_m0`: the map has none), or None: without a prior run,
    and where no bin of the chunk is empty: with every bin filled (and the fit's ``sigma2`` given,
    as :func:`chunk_mmodes` always does) the prior does not enter the fit, so its cost -- one
    transfer-matrix pass over the chunk -- is spent only on chunks with flagged time.
    """

    def __init__(self, ctx, tel, freq_hz, fi, baselines):
        self.ctx, self.tel, self.freq_hz, self.fi, self.baselines = ctx, tel, freq_hz, fi, baselines
        self.model = None

    def prior(self, binned, bin_weight, offset):
        prior_run = effective_prior(self.ctx.cfg.mmode, self.ctx.run.path)
        if prior_run is None or np.all(bin_weight > 0):
            return None
        if self.model is None:
            lmax = self.ctx.cfg.mmode.lmax
            self.model = prior_mmodes(self.tel, self.freq_hz, read_prior_alm(prior_run, self.fi, lmax), lmax,
                                      self.baselines)
        return refit_prior_m0(self.model, binned, bin_weight, offset)


def _radiometer_sigma2(ctx, vg, autos, pairs, feeds):
    """Per-sample radiometer variances ``(freq, bl)`` of the correlations of feeds ``feeds`` (pairs
    ``(p, q)``: feed p of antenna i, q of antenna j, on the autocorrelations' polarisation axis):
    ``<V_ii,p> <V_jj,q> / (dnu tau)``, where ``mmode.noise`` asks for them and the chunk's antennas
    all have autocorrelations (``auto``); else None (estimated from the fit's residual). Stokes I,
    the mean of the parallel hands, has :func:`mmflow.io.polarization.stokes_i_variance` of theirs."""
    noise = ctx.cfg.mmode.noise
    if noise == "data":
        return None, "data"
    with np.errstate(all="ignore"):
        mean = np.nanmean(autos, axis=0)  # (antenna, freq, pol)
    have = [a for a in range(len(mean)) if np.all(np.isfinite(mean[a]))]
    if noise == "auto" and not set(np.unique(pairs)) <= set(have):
        return None, "data"
    return [radiometer_variance({a: mean[a, :, p] for a in have}, pairs, vg.attrs["channel_width_hz"],
                                vg.attrs["integration_s"], str(ctx.run.store(STORES.vis)),
                                {a: mean[a, :, q] for a in have}) for p, q in feeds], "radiometer"


def _check_day(ctx, lst, n_bins, min_coverage):
    """Before any task: integrations that do not cover ``min_coverage`` of the sidereal day are not a
    day's drift scan."""
    coverage = bin_coverage(lst, n_bins)
    if coverage < min_coverage:
        raise CoverageError(str(ctx.run.store(STORES.vis)), STORES.vis.lst,
                            f"the integrations cover only {coverage:.1%} of the {n_bins} sidereal bins "
                            f"(need {min_coverage:.0%})",
                            "observe a full sidereal day, lower mmode.min_coverage, or use fewer bins")


def _check_split_coverage(bin_weight, min_coverage, source, n_bins, split):
    """A time-subset split's unflagged bins: a day flagged away would give m-modes 0."""
    coverage = float(np.median(np.mean(bin_weight > 0, axis=0)))
    if coverage < min_coverage:
        raise CoverageError(str(source), "mmode.splits", f"split '{split}': only {coverage:.1%} of {n_bins} "
                            f"sidereal bins hold unflagged data for the median baseline (need {min_coverage:.0%})",
                            f"remove {split} from mmode.splits (its data are flagged), or lower mmode.min_coverage")


def _finalize(ctx):
    """A run where most baselines miss ``mmode.min_coverage`` stops, naming the cause. The
    integrations cover the day (:func:`_check_day`, before any task), so the flags do: the input's or
    the corrections' (antennas a calibration flagged)."""
    infos = ctx.run.task_infos("mmodes").values()
    nf = ctx.open(STORES.mmodes)[STORES.mmodes.inv_var].shape[0]
    total = nf * sum(int(i.get("baselines", 0)) for i in infos)
    short = sum(int(i.get(k, 0)) for i in infos
                for k in ("dropped_low_coverage", "downweighted_low_coverage", "baselines_without_data"))
    if total and short > total / 2:
        cfg = ctx.cfg
        cal = ""
        if STORES.gains in ctx.stage.inputs and ctx.producer(STORES.gains) is not None:
            flags = ctx.read(STORES.gains.flags)
            cal = (f"; the calibrate stage flagged {np.mean(flags):.1%} of its antenna solutions "
                   f"({STORES.gains} '{STORES.gains.flags}')")
        raise CoverageError(str(ctx.run.store(STORES.vis)), STORES.vis.weights,
                            f"{short} of {total} baselines (summed over channels) keep less than "
                            f"{cfg.mmode.min_coverage:.0%} of the sidereal day after their flags, though the "
                            f"integrations cover the day: the flags, not the observation, are short{cal}",
                            "find what flags them (the input's flags; `mmflow status` for the antennas calibration "
                            "flagged), or lower mmode.min_coverage")
    return {"baselines_short_of_min_coverage": short}


STAGE = Stage(
    "mmodes",
    ("mmode", "beam", "imaging.stokes"),
    (STORES.vis,),
    (STORES.mmodes,),
    _prepare,
    _task,
    _finalize,
    reads_corrected=True,
    task_chunks={"baseline": "bl_chunk"},  # vis.zarr's baseline chunk i is read by task bl_chunk=i alone
    counters=("dropped_low_coverage", "downweighted_low_coverage", "baselines_without_data", "fits_with_prior"),
    files=prior_files,
    description="corrections on read, sidereal binning + least-squares m-modes per baseline chunk",
    cost=COST,
)
