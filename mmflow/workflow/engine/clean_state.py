"""CLEAN's settings and its state in ``clean.zarr``: what the ``clean`` stage and the products read.

The ``clean`` stage (:mod:`mmflow.workflow.stages.clean.stage`) maps the kernels of
:mod:`mmflow.imaging.clean` and :mod:`mmflow.imaging.psf` over m blocks and cycles; the
functions here turn the configuration into kernel options, build each m block's operators
(``G_kk + eps I`` factorised from ``normal.zarr`` or from the stored factors), and assemble the
stage's per-block records (residual alm, PSF columns, components) into what the driver and the
products use: one reader of CLEAN's state for the stage and the products alike.
"""
from __future__ import annotations

import time

import healpy
import numpy as np

from mmflow.conventions import healpy_alm, m_block_slice, n_alm
from mmflow.imaging import clean as ck
from mmflow.imaging import psf
from mmflow.imaging.filters import filter_mask
from mmflow.imaging.jackknife import split_variance
from mmflow.imaging.maps import default_nside
from mmflow.io.run_stores import STORES
from mmflow.mmode.normal import hermitian_block, pack_leading_upper, packed_size, upper_block
from mmflow.mmode.splits import day_splits, jackknife_kind
from mmflow.workflow.engine.geometry import split_fractions
from mmflow.workflow.engine.kernel_args import m_filters

TABLE_DECS_DEG = (0.0, 45.0, 75.0)  # always in the PSF table (Table 1's declinations)


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


def kept_coefficients(cfg, m0, m1):
    """``{m: boolean mask over l = m..lmax}`` of the coefficients the m-filters keep (``imaging``)."""
    return {m: filter_mask(m, cfg.mmode.lmax, **m_filters(cfg.imaging)) for m in range(m0, m1)}


def block_operators_from_gram(ctx, fi, m0, m1):
    """:class:`psf.BlockOperator` of each m of a block, factorised from ``normal.zarr``'s Gram."""
    cfg = ctx.cfg
    lmax, eps, keeps = cfg.mmode.lmax, cfg.imaging.eps, kept_coefficients(cfg, m0, m1)
    grams = ctx.read(STORES.normal.gram(fi, m0))

    def one(m):
        return psf.block_operator(m, hermitian_block(grams[m - m0], lmax - m0 + 1, lmax - m + 1), eps, keeps[m])

    return dict(zip(range(m0, m1), psf.map_blocks(one, range(m0, m1))))


def stored_operators(ctx, fi, m0, m1):
    """The block's operators from the stored factors (the Gram is read only where a filter
    leaves a coupling ``G_kf``: m = 1)."""
    cfg = ctx.cfg
    lmax, keeps = cfg.mmode.lmax, kept_coefficients(cfg, m0, m1)
    chol = ctx.read(STORES.clean.chol(fi, m0))
    partial = [m for m in range(m0, m1) if keeps[m].any() and not keeps[m].all()]
    grams = ctx.read(STORES.normal.gram(fi, m0)) if partial else None
    return operators_from_factors(chol, keeps, cfg.imaging.eps, lmax, m0, m1,
                                  lambda m: hermitian_block(grams[m - m0], lmax - m0 + 1, lmax - m + 1))


def operators_from_factors(chol, keeps, eps, lmax, m0, m1, full_gram=None):
    """:class:`psf.BlockOperator` per m of a block from its stored upper Cholesky factors.

    ``chol`` (m1 - m0, n0 (n0 + 1) / 2), ``n0 = lmax - m0 + 1``: the factor ``U`` of ``G_kk + eps I`` of each m
    in the top-left ``n_kept x n_kept`` corner, packed (:func:`mmflow.mmode.normal.pack_upper`); ``keeps[m]`` the
    kept coefficients; ``full_gram(m)`` the full Gram of m, called only where a filter leaves a coupling
    ``G_kf`` (m = 1).
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
        ops[m] = psf.BlockOperator(m, keep, (upper_block(chol[m - m0], lmax - m0 + 1, nk), False), eps,
                                   coupling)
    return ops


def factors_of(ops, lmax, m0, m1):
    """The block's factors as stored (``chol_b`` layout of :func:`operators_from_factors`: packed upper triangles;
    what ``potrs`` reads of a factor, its upper triangle, is kept bit for bit)."""
    n0 = lmax - m0 + 1
    chol = np.zeros((m1 - m0, packed_size(n0)), np.complex128)
    for m in range(m0, m1):
        if ops[m].cho is not None:
            pack_leading_upper(ops[m].cho[0], n0, chol[m - m0])
    return chol


def cycle_block(residual_block, rows, ops, lmax, m0, m1, weights=None):
    """One m block's part of a major cycle: ``r_new = r - H observe(sum_i c_i conj(Y_lm(r_i)))``.

    ``rows``: the cycle's ``components`` rows (x, y, z, flux; flux 0 = unused); ``weights``:
    high-pass CLEAN's ``w_l`` or None. Returns the new residual block and the seconds spent
    on the ``components`` alm and on ``observe`` (:func:`clean.observe_and_subtract`).
    """
    vecs, flux = cycle_components(rows)
    t0 = time.perf_counter()
    x = ck.component_alm(vecs, flux, lmax, m1, m0)  # only the block's m
    t1 = time.perf_counter()
    new = ck.observe_and_subtract(residual_block, x, ops, lmax, m0, m1, weights)
    return new, {"components": t1 - t0, "observe": time.perf_counter() - t1}


def cycle_components(rows):
    """``(vecs, fluxes)`` of one cycle's ``components`` rows (x, y, z, flux; flux 0 = unused)."""
    rows = np.asarray(rows, float)
    used = rows[:, 3] != 0
    return rows[used, :3], rows[used, 3]


def residual_alm(g, fi, cycle, lmax, blocks):
    """The full healpy-layout residual alm at the start of ``cycle`` (zero for m beyond mmax)."""
    out = np.zeros(n_alm(lmax), np.complex128)
    for m0, m1 in blocks:
        out[m_block_slice(lmax, m0, m1)] = g[STORES.clean.residual(fi, m0)][cycle]
    return out


def psf_alm_columns(g, fi, lmax, blocks):
    """The PSF columns ``(n_alm, n_dec)`` of the declination grid, assembled from the blocks one at a
    time (at lmax 1000 with 74 declinations the columns are 0.6 GB: the blocks are not held beside them)."""
    n_dec = g[STORES.clean.psf(fi, blocks[0][0])].shape[1]
    out = np.zeros((n_alm(lmax), n_dec), np.complex128)
    for m0, m1 in blocks:
        out[m_block_slice(lmax, m0, m1)] = g[STORES.clean.psf(fi, m0)][...]
    return out


def split_alm(ctx, fi, lmax, mmax):
    """``{split name: healpy alm}`` of the solved maps of one frequency."""
    alm = ctx.read(STORES.alm.alm, (slice(None), slice(fi, fi + 1)))[:, 0]
    return {s: healpy_alm(alm[k], lmax, mmax) for k, s in enumerate(ctx.cfg.mmode.splits)}


def jackknife_splits(ctx, fi, kind=None):
    """``(kind, splits, f_k)`` of the jackknife at frequency ``fi`` (:func:`mmflow.mmode.splits.jackknife_kind`:
    even/odd, else per-day; or the ``kind`` asked for): the splits it images and each split's share of
    the unflagged samples (``mmodes.zarr``, :func:`mmflow.workflow.engine.geometry.split_fractions`);
    ``(None, (), {})`` without one."""
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
    kind, used, fractions = jackknife
    maps = {s: healpy.alm2map(alms[s] if l_weights is None else psf.apply_l_weights(alms[s], lmax, l_weights),
                              nside, lmax=lmax) for s in used}
    return float(np.sqrt(split_variance(maps, kind, fractions, mask)))


def clean_table(g, fi):
    """The PSF table CLEAN uses (of ``H PSF`` for a high-pass CLEAN)."""
    return psf.table_from_array(g[STORES.clean.psf_table][fi, 1])


def active(peaks, threshold, opts):
    """Whether a frequency whose cycles so far started from ``peaks`` runs another cycle
    (a NaN peak: it stopped before that cycle)."""
    peaks = np.asarray(peaks, float)
    if len(peaks) and not np.isfinite(peaks[-1]):
        return False
    return opts.stop(peaks, threshold) is None


def clean_result(g, fi, opts, n=None):
    """``(state, reason)``: the :class:`clean.CleanState` (no residual) of one frequency after
    its ``n`` cycles (default: every cycle with a peak; readers of a finished stage pass
    ``n_cycles``, so that no unwritten chunk is read)."""
    thr = float(g[STORES.clean.threshold][fi])
    if n is None:
        peaks = g[STORES.clean.peaks][fi]
        n = int(np.argmin(np.isfinite(peaks))) if not np.isfinite(peaks).all() else len(peaks)
    peaks = g[STORES.clean.peaks][fi, :n]
    comps = g[STORES.clean.components][fi, :n]
    vecs, flux, cyc = [], [], []
    for c in range(n):
        v, f = cycle_components(comps[c])
        vecs.append(v)
        flux.append(f)
        cyc.append(np.full(len(f), c, int))
    def cat(xs, shape):
        return np.concatenate(xs) if xs else np.zeros(shape)

    return (ck.CleanState(None, cat(vecs, (0, 3)), cat(flux, (0,)), cat(cyc, (0,)).astype(int), peaks[:n], n),
            opts.stop(peaks[:n], thr))
