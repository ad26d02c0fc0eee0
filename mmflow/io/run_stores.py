"""The stores of a run directory, each declared once (see :mod:`mmflow.io.stores`).

==============  ======================================================================
store           arrays (dimensions)
==============  ======================================================================
vis.zarr        vis, weights (time, baseline, freq, pol); lst, time_jd (time); autos |V_ii|
                (time, antenna, freq, pol; NaN where absent or flagged); freqs_hz, pairs,
                antenna_enu; attrs ``pols`` name the pol axis (xx, yy | rr, ll | I | one
                hand); vis_cross, weights_cross (time, baseline, freq, cross_pol) where
                ingested files hold the cross hands, named by attrs ``cross_pols`` (xy, yx |
                rl, lr). Never rewritten by corrections.
mmodes.zarr     mmodes (split, freq, m, 2, baseline); inv_var (freq, baseline); n_samples
                (split, freq, baseline): unflagged integrations of each split (its share f_k)
partials.zarr   f{F}/gram_b{M0} (group, m, l, l'); f{F}/rhs (group, split, m, l);
                f{F}/vhv (group, split, m): one partial sum per fixed baseline group
normal.zarr     f{F}/gram_b{M0} (m, l, l'); rhs (split, freq, m, l); vhv (split, freq, m)
alm.zarr        alm (split, freq, m, l); lcurve (freq, m, eps, 2); fraction_above (freq, m);
                eps_grid (eps)
transfer.zarr   f{F}/order (baseline); f{F}/B_m{M} (2, baseline, l)   [transfer.mode=store]
models.zarr     components (freq, source, component, 6); cost (freq, source, 3); iterations,
                n_integrations (freq, source)   [models stage]
==============  ======================================================================

Gram blocks are stored per m block (``m0 <= m < m1``) padded to the block's largest size
``lmax - m0 + 1``: a few hundred arrays at lmax 1000 instead of one per m.
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import m_block_slice, m_blocks
from mmflow.io.stores import ArraySpec, StoreSpec


def vis_store(n_time, pairs, freqs_hz, antenna_enu, attrs, time_chunk, baseline_chunk):
    """``attrs["pols"]`` names the polarisation axis, ``attrs["cross_pols"]`` (optional) the cross hands' axis."""
    nbl, nf, n_ant, npol = len(pairs), len(freqs_hz), len(antenna_enu), len(attrs["pols"])
    ch = (time_chunk, min(baseline_chunk, nbl), nf, npol)
    dims = ("time", "baseline", "freq", "pol")
    ncross = len(attrs.get("cross_pols") or [])
    cross = () if not ncross else (
        ArraySpec("vis_cross", dims[:3] + ("cross_pol",), (n_time, nbl, nf, ncross), ch[:3] + (ncross,), "complex64"),
        ArraySpec("weights_cross", dims[:3] + ("cross_pol",), (n_time, nbl, nf, ncross), ch[:3] + (ncross,),
                  "float32"))
    return StoreSpec("vis.zarr", (
        ArraySpec("vis", dims, (n_time, nbl, nf, npol), ch, "complex64"),
        ArraySpec("weights", dims, (n_time, nbl, nf, npol), ch, "float32"),
        ArraySpec("lst", ("time",), (n_time,), (time_chunk,), "float64", np.nan),
        ArraySpec("time_jd", ("time",), (n_time,), (time_chunk,), "float64", np.nan),
        ArraySpec("autos", ("time", "antenna", "freq", "pol"), (n_time, n_ant, nf, npol),
                  (time_chunk, n_ant, nf, npol), "float32", np.nan),
        ArraySpec("freqs_hz", ("freq",), (nf,), (nf,), "float64", data=freqs_hz),
        ArraySpec("pairs", ("baseline", "ant"), (nbl, 2), (nbl, 2), "int32", data=pairs),
        ArraySpec("antenna_enu", ("antenna", "enu"), np.shape(antenna_enu), np.shape(antenna_enu), "float64",
                  data=antenna_enu),
    ) + cross, attrs)


def mmodes_store(n_split, nf, mmax, nbl, baseline_chunk, attrs):
    """``n_samples``: each split's unflagged integrations per frequency and baseline (the bins'
    summed 0/1 weights), from which the jackknives take each split's share ``f_k``
    (:func:`mmflow.mmode.splits.split_shares`)."""
    ch = min(baseline_chunk, nbl)
    return StoreSpec("mmodes.zarr", (
        ArraySpec("mmodes", ("split", "freq", "m", "pm", "baseline"), (n_split, nf, mmax + 1, 2, nbl),
                  (n_split, nf, mmax + 1, 2, ch), "complex128"),
        ArraySpec("inv_var", ("freq", "baseline"), (nf, nbl), (nf, ch), "float64"),
        ArraySpec("n_samples", ("split", "freq", "baseline"), (n_split, nf, nbl), (n_split, nf, ch), "int64"),
    ), attrs)


def gram_name(fi, m0):
    return f"f{fi}/gram_b{m0:05d}"


def partials_store(nf, n_groups, lmax, mmax, m_block, n_split, dtype):
    arrays = []
    for fi in range(nf):
        for m0, m1 in m_blocks(mmax, m_block):
            n = lmax - m0 + 1
            arrays.append(ArraySpec(gram_name(fi, m0), ("group", "m", "l", "l2"), (n_groups, m1 - m0, n, n),
                                    (1, m1 - m0, n, n), dtype))
        arrays.append(ArraySpec(f"f{fi}/rhs", ("group", "split", "m", "l"), (n_groups, n_split, mmax + 1, lmax + 1),
                                (1, n_split, mmax + 1, lmax + 1), dtype))
        arrays.append(ArraySpec(f"f{fi}/vhv", ("group", "split", "m"), (n_groups, n_split, mmax + 1),
                                (1, n_split, mmax + 1), "float64"))
    return StoreSpec("partials.zarr", tuple(arrays))


def normal_store(nf, lmax, mmax, m_block, n_split, gram_dtype="complex128"):
    """Reduced normal equations. Grams keep the partials' precision (``gram_dtype``: complex64
    for float32 transfer, half the bytes to write and read; summed in complex128 and rounded
    once, so one group's Gram is the engine's bit for bit); right-hand sides are complex128."""
    arrays = []
    for fi in range(nf):
        for m0, m1 in m_blocks(mmax, m_block):
            n = lmax - m0 + 1
            arrays.append(ArraySpec(gram_name(fi, m0), ("m", "l", "l2"), (m1 - m0, n, n), (m1 - m0, n, n),
                                    gram_dtype))
    arrays += [
        ArraySpec("rhs", ("split", "freq", "m", "l"), (n_split, nf, mmax + 1, lmax + 1),
                  (n_split, 1, m_block, lmax + 1), "complex128"),
        ArraySpec("vhv", ("split", "freq", "m"), (n_split, nf, mmax + 1), (n_split, 1, m_block), "float64"),
    ]
    return StoreSpec("normal.zarr", tuple(arrays))


def alm_store(nf, lmax, mmax, m_block, n_split, eps_grid):
    n_eps = len(eps_grid)
    return StoreSpec("alm.zarr", (
        ArraySpec("alm", ("split", "freq", "m", "l"), (n_split, nf, mmax + 1, lmax + 1),
                  (n_split, 1, m_block, lmax + 1), "complex128"),
        ArraySpec("lcurve", ("freq", "m", "eps", "norm"), (nf, mmax + 1, n_eps, 2), (1, m_block, n_eps, 2),
                  "float64"),
        ArraySpec("fraction_above", ("freq", "m"), (nf, mmax + 1), (1, m_block), "float64"),
        ArraySpec("eps_grid", ("eps",), (n_eps,), (n_eps,), "float64", data=eps_grid),
    ))


def transfer_store(nf, nbl, lmax, mmax, baseline_chunk, dtype, orders):
    arrays = []
    for fi in range(nf):
        arrays.append(ArraySpec(f"f{fi}/order", ("baseline",), (nbl,), (nbl,), "int64", data=orders[fi]))
        for m in range(mmax + 1):
            arrays.append(ArraySpec(f"f{fi}/B_m{m:05d}", ("pm", "baseline", "l"), (2, nbl, lmax - m + 1),
                                    (2, min(baseline_chunk, nbl), lmax - m + 1), dtype))
    return StoreSpec("transfer.zarr", tuple(arrays))


def gains_store(n_interval, nf, n_ant, npol, n_time, solve_rows, apply_rows, attrs):
    """``gains.zarr`` of the calibrate stage: per solution interval (``solve_rows``: the
    integrations it was solved on; ``apply_rows``: those it corrects) and frequency the gains,
    flags and diagnostics; ``ripple`` r(t) per integration (1 where not corrected)."""
    per = (1, 1, n_ant, npol)
    sol = ("interval", "freq", "antenna", "pol")
    return StoreSpec("gains.zarr", (
        ArraySpec("gains", sol, (n_interval, nf, n_ant, npol), per, "complex128"),
        ArraySpec("flags", sol, (n_interval, nf, n_ant, npol), per, "bool"),
        ArraySpec("chi2", sol, (n_interval, nf, n_ant, npol), per, "float64"),
        ArraySpec("iterations", ("interval", "freq", "pol"), (n_interval, nf, npol), (1, 1, npol), "int32"),
        ArraySpec("converged", ("interval", "freq", "pol"), (n_interval, nf, npol), (1, 1, npol), "bool"),
        ArraySpec("ripple", ("time", "freq", "antenna", "pol"), (n_time, nf, n_ant, npol), (n_time, 1, n_ant, npol),
                  "float64"),
        ArraySpec("solve_rows", ("interval", "edge"), (n_interval, 2), (n_interval, 2), "int64", data=solve_rows),
        ArraySpec("apply_rows", ("interval", "edge"), (n_interval, 2), (n_interval, 2), "int64", data=apply_rows),
    ), attrs)


def peel_store(n_time, nf, n_src, n_ant, npol, time_chunk, attrs):
    """``peel.zarr``: per integration, frequency and source the DD gains, the fitted flux scale,
    the mode used (0 skip, 1 peel, 2 subtract), the guard's verdict and fluxes, and convergence."""
    dims = ("time", "freq", "source", "pol")
    shape, ch = (n_time, nf, n_src, npol), (time_chunk, 1, n_src, npol)
    return StoreSpec("peel.zarr", (
        ArraySpec("dd_gains", ("time", "freq", "source", "antenna", "pol"), (n_time, nf, n_src, n_ant, npol),
                  (time_chunk, 1, n_src, n_ant, npol), "complex128"),
        ArraySpec("scale", dims, shape, ch, "float64"),
        ArraySpec("mode", dims, shape, ch, "int8"),
        ArraySpec("guard", dims, shape, ch, "bool"),
        ArraySpec("measured", dims, shape, ch, "float64"),
        ArraySpec("removed", dims, shape, ch, "float64"),
        ArraySpec("converged", dims, shape, ch, "bool"),
    ), attrs)


#: columns of models.zarr's ``components``
MODEL_COLUMNS = ("x_arcmin", "y_arcmin", "flux_jy", "fwhm_major_arcmin", "fwhm_minor_arcmin", "pa_deg")
#: columns of models.zarr's ``cost``
MODEL_COSTS = ("point", "start", "fitted")


def models_store(nf, n_src, n_comp, attrs):
    """``models.zarr`` of the models stage: per frequency and source the fitted Gaussian components
    (:data:`MODEL_COLUMNS`; offsets east/north of the catalogued position, fluxes renormalised to the
    published spectrum; flux 0 = no component), the aperture cost of the point model, of the start
    and of the fit (:data:`MODEL_COSTS`), Nelder-Mead iterations and the integrations used."""
    return StoreSpec("models.zarr", (
        ArraySpec("components", ("freq", "source", "component", "column"), (nf, n_src, n_comp, len(MODEL_COLUMNS)),
                  (1, 1, n_comp, len(MODEL_COLUMNS)), "float64"),
        ArraySpec("cost", ("freq", "source", "kind"), (nf, n_src, len(MODEL_COSTS)), (1, 1, len(MODEL_COSTS)),
                  "float64"),
        ArraySpec("iterations", ("freq", "source"), (nf, n_src), (1, 1), "int64"),
        ArraySpec("n_integrations", ("freq", "source"), (nf, n_src), (1, 1), "int64"),
    ), attrs)


def terrestrial_store(n_chunks, n_time, nf, nbl, n_comp, n_ant, npol, time_chunk):
    """``terrestrial.zarr``: per time chunk the weighted sums of the (calibrated, peeled) data,
    the rank-1 patterns fitted to their average, and per integration the templates' amplitudes."""
    return StoreSpec("terrestrial.zarr", (
        ArraySpec("sum_vis", ("chunk", "freq", "baseline", "pol"), (n_chunks, nf, nbl, npol), (1, nf, nbl, npol),
                  "complex128"),
        ArraySpec("sum_weight", ("chunk", "freq", "baseline", "pol"), (n_chunks, nf, nbl, npol), (1, nf, nbl, npol),
                  "float64"),
        ArraySpec("patterns", ("freq", "component", "antenna", "pol"), (nf, n_comp, n_ant, npol),
                  (nf, n_comp, n_ant, npol), "complex128"),
        ArraySpec("amplitudes", ("time", "freq", "component", "pol"), (n_time, nf, n_comp, npol),
                  (time_chunk, nf, n_comp, npol), "float64"),
    ))


# ----------------------------------------------------------------------------- clean.zarr

CLEAN_STOPS = ("threshold", "rel_threshold", "stall", "max_cycles")  # codes of clean.zarr's ``stop``
NOISE_FIELDS = ("jy_per_sr", "kelvin", "mjy_per_beam", "beam_solid_angle_sr")  # columns of clean.zarr's ``noise``


def clean_store(nf, lmax, mmax, m_block, n_dec, max_cycles, n_peaks, npix, keep_factors):
    """``clean.zarr``: the CLEAN stage's factors, PSFs, per-cycle state and results.

    Per frequency ``F`` and m block ``M0`` (healpy layout within the block):
    ``f{F}/chol_b{M0}`` (m, l, l2) Cholesky factors of ``G_kk + eps I`` [keep_factors];
    ``f{F}/psf_b{M0}`` (alm, dec) PSF columns of the declination grid;
    ``f{F}/residual_b{M0}`` (cycle, alm) the residual alm at the start of each cycle (one chunk
    per cycle, never rewritten: a killed cycle is redone from the one before).
    Per frequency: ``psf_table`` (freq, kind, dec, 5: dec, peak, major, minor, pa; kind 0 the
    PSF, kind 1 the PSF CLEAN uses, ``H PSF`` for a high-pass CLEAN); ``noise``
    (freq, 4: :data:`NOISE_FIELDS`); ``threshold`` (freq) Jy/sr; ``peaks`` (freq, cycle) the
    residual peak each cycle started from; ``components`` (freq, cycle, peak, 4: x, y, z, flux
    in Jy; flux 0 = none); ``restored`` (freq, pixel) the restored map (frame of date, Jy/sr);
    ``n_cycles`` and ``stop`` (:data:`CLEAN_STOPS` index) per frequency.
    """
    arrays = []
    for fi in range(nf):
        for m0, m1 in m_blocks(mmax, m_block):
            sl = m_block_slice(lmax, m0, m1)
            n, k = lmax - m0 + 1, sl.stop - sl.start
            if keep_factors:
                arrays.append(ArraySpec(f"f{fi}/chol_b{m0:05d}", ("m", "l", "l2"), (m1 - m0, n, n), (m1 - m0, n, n),
                                        "complex128"))
            arrays.append(ArraySpec(f"f{fi}/psf_b{m0:05d}", ("alm", "dec"), (k, n_dec), (k, n_dec), "complex128"))
            arrays.append(ArraySpec(f"f{fi}/residual_b{m0:05d}", ("cycle", "alm"), (max_cycles + 1, k), (1, k),
                                    "complex128"))
    arrays += [
        ArraySpec("psf_table", ("freq", "kind", "dec", "column"), (nf, 2, n_dec, 5), (1, 2, n_dec, 5), "float64",
                  np.nan),
        ArraySpec("noise", ("freq", "quantity"), (nf, len(NOISE_FIELDS)), (1, len(NOISE_FIELDS)), "float64", np.nan),
        ArraySpec("threshold", ("freq",), (nf,), (1,), "float64", np.nan),
        ArraySpec("peaks", ("freq", "cycle"), (nf, max_cycles), (1, 1), "float64", np.nan),
        ArraySpec("components", ("freq", "cycle", "peak", "xyzf"), (nf, max_cycles, n_peaks, 4), (1, 1, n_peaks, 4),
                  "float64"),
        ArraySpec("restored", ("freq", "pixel"), (nf, npix), (1, npix), "float64"),
        ArraySpec("n_cycles", ("freq",), (nf,), (1,), "int64"),
        ArraySpec("stop", ("freq",), (nf,), (1,), "int64", -1),
    ]
    return StoreSpec("clean.zarr", tuple(arrays))
