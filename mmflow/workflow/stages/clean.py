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
  stopped (:func:`clean.stop_reason`), synthesise the residual map and pick this cycle's components (:func:`clean.plan_cycle`);
* cycle tasks, one per (frequency, m block): ``residual[c + 1] = residual[c] - observe(x)``
  (:func:`clean.observe_and_subtract`), ``x`` the block of the cycle's components' alm;
* finalize: the restored map (frame of date) per frequency.

Every cycle's residual and components go to their own chunks of ``clean.zarr`` (nothing is
rewritten), so a killed cycle is planned and run again identically from the one before.
"""
from __future__ import annotations

import time

import numpy as np

from mmflow.conventions import healpy_alm, n_alm
from mmflow.imaging import clean as ck
from mmflow.imaging import psf
from mmflow.imaging.filters import filter_mask
from mmflow.imaging.maps import default_nside
from mmflow.io.run_stores import CLEAN_STOPS, NOISE_FIELDS, clean_store, gram_name, m_blocks
from mmflow.workflow.geometry import mmax_of, split_fractions
from mmflow.workflow.kernel_args import m_filters
from mmflow.workflow.stages.base import Stage, register
from mmflow.workflow.task_key import TaskKey

CLEAN_CONFIG = ("mmode.lmax", "mmode.mmax", "mmode.splits", "transfer.m_block", "imaging", "clean")
TABLE_DECS_DEG = (0.0, 45.0, 75.0)  # always in the PSF table (Table 1's declinations)


# ----------------------------------------------------------------------------- settings

def clean_options(c):
    """:class:`clean.CleanOptions` from the ``clean`` configuration section."""
    return ck.CleanOptions(n_peaks=c.peaks_per_cycle, min_sep_deg=c.min_separation_deg, gain=c.gain,
                           k_sigma=c.threshold_sigma, absolute=c.absolute, peak_frac=c.peak_fraction,
                           max_cycles=c.max_cycles, rel_threshold=c.rel_threshold, stall_cycles=c.stall_cycles,
                           stall_frac=c.stall_fraction)


def highpass(cfg):
    """``w_l`` of a high-pass CLEAN (:func:`psf.highpass_weights`), or None."""
    c = cfg.clean
    return None if c.highpass_lmin is None else psf.highpass_weights(cfg.mmode.lmax, c.highpass_lmin, c.highpass_width)


def clean_nside(cfg):
    return cfg.clean.nside or 2 * default_nside(cfg.mmode.lmax)


def psf_decs_deg(lat_deg, step_deg):
    """The PSF table's declinations: the lowest seen declination (rounded up to ``step``) to
    the pole in ``step`` steps, plus Table 1's 0, +45, +75."""
    lo = np.rad2deg(ck.never_seen_dec_min(np.deg2rad(lat_deg)))
    grid = np.arange(step_deg * np.ceil(lo / step_deg), 90.0 + 1e-9, step_deg)
    return np.unique(np.round(np.concatenate([grid, TABLE_DECS_DEG]), 9))


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
    nf = ctx.open("alm.zarr")["alm"].shape[1]
    n_dec = len(psf_decs_deg(_lat(ctx), cfg.clean.psf_dec_step_deg))
    ctx.create(clean_store(nf, lmax, mmax, cfg.transfer.m_block, n_dec, cfg.clean.max_cycles,
                           cfg.clean.peaks_per_cycle, 12 * clean_nside(cfg) ** 2, cfg.clean.keep_factors))
    return [TaskKey(freq=fi, m_block=m0) for fi in range(nf) for m0, _ in blocks]


def _keeps(cfg, m0, m1):
    return {m: filter_mask(m, cfg.mmode.lmax, **m_filters(cfg.imaging)) for m in range(m0, m1)}


def block_operators_from_gram(ctx, fi, m0, m1):
    """:class:`psf.BlockOperator` of each m of a block, factorised from ``normal.zarr``'s Gram."""
    from mmflow.mmode.normal import hermitian_full

    cfg = ctx.cfg
    lmax, eps, keeps = cfg.mmode.lmax, cfg.imaging.eps, _keeps(cfg, m0, m1)
    grams = ctx.read("normal.zarr", gram_name(fi, m0))

    def one(m):
        n = lmax - m + 1
        return psf.block_operator(m, hermitian_full(grams[m - m0, :n, :n]), eps, keeps[m])

    return dict(zip(range(m0, m1), psf.map_blocks(one, range(m0, m1))))


def stored_operators(ctx, fi, m0, m1):
    """The block's operators from the stored factors (the Gram is read only where a filter
    leaves a coupling ``G_kf``: m = 1)."""
    from mmflow.mmode.normal import hermitian_full

    cfg = ctx.cfg
    lmax, keeps = cfg.mmode.lmax, _keeps(cfg, m0, m1)
    chol = ctx.read("clean.zarr", f"f{fi}/chol_b{m0:05d}")
    partial = [m for m in range(m0, m1) if keeps[m].any() and not keeps[m].all()]
    grams = ctx.read("normal.zarr", gram_name(fi, m0)) if partial else None
    return operators_from_factors(chol, keeps, cfg.imaging.eps, lmax, m0, m1,
                                  lambda m: hermitian_full(grams[m - m0, :lmax - m + 1, :lmax - m + 1]))


def operators_from_factors(chol, keeps, eps, lmax, m0, m1, full_gram=None):
    """:class:`psf.BlockOperator` per m of a block from its stored upper Cholesky factors.

    ``chol`` (m1 - m0, n0, n0): the factor ``U`` of ``G_kk + eps I`` of each m in the top-left
    ``n_kept x n_kept`` corner; ``keeps[m]`` the kept coefficients; ``full_gram(m)`` the full
    Gram of m, called only where a filter leaves a coupling ``G_kf`` (m = 1).
    """
    ops = {}
    for m in range(m0, m1):
        keep = keeps[m]
        nk = int(keep.sum())
        if nk == 0:
            ops[m] = psf.BlockOperator(m, keep, None, eps)
            continue
        coupling = None
        if not keep.all():
            coupling = np.ascontiguousarray(full_gram(m)[np.ix_(keep, ~keep)])
        ops[m] = psf.BlockOperator(m, keep, (chol[m - m0, :nk, :nk], False), eps, coupling)
    return ops


def factors_of(ops, lmax, m0, m1):
    """The block's factors as stored (``chol_b`` layout of :func:`operators_from_factors`)."""
    n0 = lmax - m0 + 1
    chol = np.zeros((m1 - m0, n0, n0), np.complex128)
    for m in range(m0, m1):
        op = ops[m]
        if op.cho is not None:
            nk = len(op.cho[0])
            chol[m - m0, :nk, :nk] = op.cho[0]
    return chol


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
    g = ctx.open("clean.zarr", mode="r+")
    t0 = time.perf_counter()
    ops = block_operators_from_gram(ctx, fi, m0, m1)
    t_factor = time.perf_counter() - t0
    if cfg.clean.keep_factors:
        ctx.write(g, f"f{fi}/chol_b{m0:05d}", (), factors_of(ops, lmax, m0, m1))
    t0 = time.perf_counter()
    decs = np.deg2rad(psf_decs_deg(_lat(ctx), cfg.clean.psf_dec_step_deg))
    ctx.write(g, f"f{fi}/psf_b{m0:05d}", (), psf.psf_columns(ops, lmax, psf.table_vectors(decs), m0, m1))
    t_psf = time.perf_counter() - t0
    dirty = _ml_to_block(ctx.read("alm.zarr", "alm", (slice(0, 1), slice(fi, fi + 1), slice(m0, m1)))[0, 0],
                         lmax, m0, m1)
    w = highpass(cfg)
    if w is not None:
        dirty = dirty * np.concatenate([w[m:] for m in range(m0, m1)])
    ctx.write(g, f"f{fi}/residual_b{m0:05d}", (slice(0, 1),), dirty[None])
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
    rows = ctx.read("clean.zarr", "components", (slice(fi, fi + 1), slice(c, c + 1)))[0, 0]
    name = f"f{fi}/residual_b{m0:05d}"
    resid = ctx.read("clean.zarr", name, (slice(c, c + 1),))[0]
    new, t = cycle_block(resid, rows, ops, lmax, m0, m1, highpass(cfg))
    ctx.write(ctx.open("clean.zarr", mode="r+"), name, (slice(c + 1, c + 2),), new[None])
    return {"m": [m0, m1], "operators_s": round(t_ops, 4), "components_s": round(t["components"], 4),
            "observe_s": round(t["observe"], 4)}


def cycle_block(residual_block, rows, ops, lmax, m0, m1, weights=None):
    """One m block's part of a major cycle: ``r_new = r - H observe(sum_i c_i conj(Y_lm(r_i)))``.

    ``rows``: the cycle's ``components`` rows (x, y, z, flux; flux 0 = unused); ``weights``:
    high-pass CLEAN's ``w_l`` or None. Returns the new residual block and the seconds spent
    on the ``components`` alm and on ``observe`` (:func:`clean.observe_and_subtract`).
    """
    vecs, flux = cycle_components(rows)
    t0 = time.perf_counter()
    x = ck.component_alm(vecs, flux, lmax, m1)[psf.block_range(lmax, m0, m1)]
    t1 = time.perf_counter()
    new = ck.observe_and_subtract(residual_block, x, ops, lmax, m0, m1, weights)
    return new, {"components": t1 - t0, "observe": time.perf_counter() - t1}


def cycle_components(rows):
    """``(vecs, fluxes)`` of one cycle's ``components`` rows (x, y, z, flux; flux 0 = unused)."""
    rows = np.asarray(rows, float)
    used = rows[:, 3] != 0
    return rows[used, :3], rows[used, 3]


# ----------------------------------------------------------------------------- the driver

def residual_alm(g, fi, cycle, lmax, blocks):
    """The full healpy-layout residual alm at the start of ``cycle`` (zero for m beyond mmax)."""
    out = np.zeros(n_alm(lmax), np.complex128)
    for m0, m1 in blocks:
        out[psf.block_range(lmax, m0, m1)] = g[f"f{fi}/residual_b{m0:05d}"][cycle]
    return out


def psf_alm_columns(g, fi, lmax, blocks):
    """The PSF columns ``(n_alm, n_dec)`` of the declination grid, assembled from the blocks."""
    parts = {m0: g[f"f{fi}/psf_b{m0:05d}"][...] for m0, _ in blocks}
    out = np.zeros((n_alm(lmax), next(iter(parts.values())).shape[1]), np.complex128)
    for m0, m1 in blocks:
        out[psf.block_range(lmax, m0, m1)] = parts[m0]
    return out


def split_alm(ctx, fi, lmax, mmax):
    """``{split name: healpy alm}`` of the solved maps of one frequency."""
    alm = ctx.read("alm.zarr", "alm", (slice(None), slice(fi, fi + 1)))[:, 0]
    return {s: healpy_alm(alm[k], lmax, mmax) for k, s in enumerate(ctx.cfg.mmode.splits)}


def jackknife_splits(ctx, fi, kind=None):
    """``(kind, splits, f_k)`` of the jackknife at frequency ``fi`` (:func:`mmflow.mmode.splits.jackknife_kind`:
    even/odd, else per-day; or the ``kind`` asked for): the splits it images and each split's share of
    the unflagged samples (``mmodes.zarr``, :func:`mmflow.workflow.geometry.split_fractions`);
    ``(None, (), {})`` without one."""
    from mmflow.mmode.splits import day_splits, jackknife_kind

    splits = ctx.cfg.mmode.splits
    kind = jackknife_kind(splits) if kind is None else kind
    if kind == "even_odd" and {"even", "odd"} <= set(splits):
        return kind, ("full", "even", "odd"), {}
    if kind == "per_day" and day_splits(splits):
        used = ("full",) + tuple(day_splits(splits).values())
        return kind, used, split_fractions(ctx, fi)
    return None, (), {}


def jackknife_sigma(alms, jackknife, lmax, nside, mask, l_weights=None):
    """The full map's jackknife sigma (Jy/sr) over ``mask`` (frame of date) from the split alm
    ``{name: healpy alm}`` (:func:`mmflow.imaging.jackknife.split_variance`); ``jackknife`` from
    :func:`jackknife_splits`; ``l_weights``: of high-pass CLEAN's ``H`` maps (None: the maps)."""
    import healpy

    from mmflow.imaging.jackknife import split_variance

    kind, used, fractions = jackknife
    maps = {s: healpy.alm2map(alms[s] if l_weights is None else psf.apply_l_weights(alms[s], lmax, l_weights),
                              nside, lmax=lmax) for s in used}
    return float(np.sqrt(split_variance(maps, kind, fractions, mask)))


def _setup_tables(ctx, g):
    """Cycle 0 on the driver: PSF tables, jackknife noise and the stop threshold per frequency."""
    from mmflow.imaging.jackknife import beam_noise
    from mmflow.sky import units

    cfg = ctx.cfg
    c = cfg.clean
    lmax, mmax, blocks = _geometry(ctx)
    decs = np.deg2rad(psf_decs_deg(_lat(ctx), c.psf_dec_step_deg))
    w = highpass(cfg)
    nside = clean_nside(cfg)
    mask = ck.observed_mask(nside, ck.never_seen_dec_min(np.deg2rad(_lat(ctx))))
    freqs = ctx.read("vis.zarr", "freqs_hz")
    for fi in range(g["threshold"].shape[0]):
        jk = jackknife_splits(ctx, fi)
        cols = psf_alm_columns(g, fi, lmax, blocks)
        tables = [psf.fit_psf_columns(cols, lmax, decs)]
        tables.append(tables[0] if w is None else psf.fit_psf_columns(psf.apply_l_weights(cols, lmax, w), lmax, decs))
        ctx.write(g, "psf_table", (slice(fi, fi + 1),), np.stack([psf.table_to_array(t) for t in tables])[None],
                  allow_nan=True)
        noise, sigma_clean = np.full(len(NOISE_FIELDS), np.nan), None
        if jk[0] is not None:
            alms = split_alm(ctx, fi, lmax, mmax)
            sigma_clean = jackknife_sigma(alms, jk, lmax, nside, mask)
            nz = beam_noise(sigma_clean, float(freqs[fi]), tables[0])
            noise = np.array([nz[k] for k in NOISE_FIELDS])
            if w is not None:  # CLEAN sees H maps: their noise sets its threshold
                sigma_clean = jackknife_sigma(alms, jk, lmax, nside, mask, w)
        ctx.write(g, "noise", (slice(fi, fi + 1),), noise[None], allow_nan=True)
        if c.threshold is not None:
            thr = float(units.convert(c.threshold, c.threshold_unit, "Jy/sr", float(freqs[fi])))
        else:
            thr = c.threshold_sigma * sigma_clean if sigma_clean is not None else 0.0
        ctx.write(g, "threshold", (slice(fi, fi + 1),), np.array([thr]))


def clean_table(g, fi):
    """The PSF table CLEAN uses (of ``H PSF`` for a high-pass CLEAN)."""
    return psf.table_from_array(g["psf_table"][fi, 1])


def active(peaks, threshold, opts):
    """Whether a frequency whose cycles so far started from ``peaks`` runs another cycle
    (a NaN peak: it stopped before that cycle)."""
    peaks = np.asarray(peaks, float)
    if len(peaks) and not np.isfinite(peaks[-1]):
        return False
    return opts.stop(peaks, threshold) is None


def _next_cycle(ctx, cycle):
    cfg = ctx.cfg
    lmax, _, blocks = _geometry(ctx)
    g = ctx.open("clean.zarr", mode="r+")
    if cycle == 0:
        _setup_tables(ctx, g)
    opts, nside = clean_options(cfg.clean), clean_nside(cfg)
    mask = ck.observed_mask(nside, ck.never_seen_dec_min(np.deg2rad(_lat(ctx))))
    keys = []
    for fi in range(g["threshold"].shape[0]):
        thr = float(g["threshold"][fi])
        if not active(g["peaks"][fi, :cycle], thr, opts):
            continue
        vecs, flux, peak, _ = ck.plan_cycle(residual_alm(g, fi, cycle, lmax, blocks), lmax, clean_table(g, fi), mask,
                                            nside, opts, thr)
        rows = np.zeros((opts.n_peaks, 4))
        rows[:len(flux), :3], rows[:len(flux), 3] = vecs, flux
        ctx.write(g, "components", (slice(fi, fi + 1), slice(cycle, cycle + 1)), rows[None, None])
        ctx.write(g, "peaks", (slice(fi, fi + 1), slice(cycle, cycle + 1)), np.array([[peak]]))
        keys += [TaskKey(freq=fi, m_block=m0) for m0, _ in blocks]
    return keys or None


def clean_result(g, fi, opts, n=None):
    """``(state, reason)``: the :class:`clean.CleanState` (no residual) of one frequency after
    its ``n`` cycles (default: every cycle with a peak; readers of a finished stage pass
    ``n_cycles``, so that no unwritten chunk is read)."""
    thr = float(g["threshold"][fi])
    if n is None:
        peaks = g["peaks"][fi]
        n = int(np.argmin(np.isfinite(peaks))) if not np.isfinite(peaks).all() else len(peaks)
    peaks = g["peaks"][fi, :n]
    comps = g["components"][fi, :n]
    vecs, flux, cyc = [], [], []
    for c in range(n):
        v, f = cycle_components(comps[c])
        vecs.append(v)
        flux.append(f)
        cyc.append(np.full(len(f), c, int))
    cat = (lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape))
    return (ck.CleanState(None, cat(vecs, (0, 3)), cat(flux, (0,)), cat(cyc, (0,)).astype(int), peaks[:n], n),
            opts.stop(peaks[:n], thr))


def _finalize(ctx):
    import healpy

    cfg = ctx.cfg
    lmax, mmax, blocks = _geometry(ctx)
    g = ctx.open("clean.zarr", mode="r+")
    opts, nside, w = clean_options(cfg.clean), clean_nside(cfg), highpass(cfg)
    out = {}
    for fi in range(g["threshold"].shape[0]):
        state, reason = clean_result(g, fi, opts)
        state.residual_alm = residual_alm(g, fi, state.cycle, lmax, blocks)
        table = clean_table(g, fi)
        if w is None:
            restored = ck.restore_map(healpy.alm2map(state.residual_alm, nside, lmax=lmax), state.comp_vec,
                                      state.comp_flux, table)
        else:
            restored = ck.restore_highpass(split_alm(ctx, fi, lmax, mmax)["full"], state, table, w, lmax, nside)
        ctx.write(g, "restored", (slice(fi, fi + 1),), restored[None])
        ctx.write(g, "n_cycles", (slice(fi, fi + 1),), np.array([state.cycle]))
        ctx.write(g, "stop", (slice(fi, fi + 1),), np.array([CLEAN_STOPS.index(reason) if reason else -1]))
        out[f"f{fi}"] = {"cycles": state.cycle, "stop": reason, "components": int(len(state.comp_flux)),
                         "first_peak_jy_sr": float(state.peaks[0]) if state.cycle else None,
                         "last_peak_jy_sr": float(state.peaks[-1]) if state.cycle else None,
                         "threshold_jy_sr": float(g["threshold"][fi])}
    return out


register(Stage("clean", CLEAN_CONFIG, ("vis.zarr", "mmodes.zarr", "normal.zarr", "alm.zarr"), ("clean.zarr",), _prepare,
               _task, _finalize, enabled=lambda cfg: cfg.clean.enabled, kind="iterative", next_cycle=_next_cycle,
               description="m-mode CLEAN: PSF by declination, major cycles over m blocks, jackknife threshold"))
