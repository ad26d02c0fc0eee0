"""``mmflow bench clean``: PSF and CLEAN timings at the paper's lmax, printed as JSON.

Measured in one run, beside this machine's DGEMM/ZGEMM-class peak (``gemm_gflops``):

* the Cholesky factors of every block ``G_m + eps I`` (what the CLEAN stage either keeps or
  recomputes per m block), their memory, and the factorisation rate;
* the PSF at one declination: the point source's alm, observing it through the factors, the
  elliptical fit of its main lobe;
* one CLEAN major cycle as the ``clean`` stage runs it (:func:`stage_cycle`, the stage's own
  functions): synthesis and peak finding on the driver, then per m block reading the stored
  factors, the component alm and observe-and-subtract, the blocks on ``n_threads()`` threads;
* a projection for the paper's channel to the threshold, stated as a projection.

The Grams are synthetic (the paper array's real ones at lmax 1000 take minutes and gigabytes
more (docs/performance.md), ``mmflow bench table1``; these keep this bench quick and
self-contained): ``G_m = D K D`` with ``D = diag(exp(-l^2 / 2 L^2))`` and ``K`` a Gaussian
Toeplitz kernel in l (positive definite, Hermitian). Factorising and observing cost the same
for any Gram of that size; the PSF's shape is not the paper's.
"""
from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time

import healpy
import numpy as np
import scipy.linalg as sla
import zarr

from mmflow.bench.engine import BEAM
from mmflow.conventions import m_block_slice, m_blocks, m_slice, radec_to_vec
from mmflow.imaging import clean, psf
from mmflow.imaging.filters import filter_mask
from mmflow.imaging.maps import default_nside
from mmflow.io.run_stores import STORES
from mmflow.machine import gemm_gflops, machine
from mmflow.mmode.engine import accumulate_normal_equations
from mmflow.sky.diffuse import band_limited_random_alm, synthetic_sky_kelvin
from mmflow.sky.harmonics import point_sources_alm
from mmflow.telescope import Telescope, ovro_lwa_layout
from mmflow.threads import n_threads
from mmflow.workflow.engine import clean_state as clean_stage
from mmflow.workflow.stages.transfer.settings import TransferConfig

L_SCALE = 0.7  # the synthetic Grams' D_ll falls as exp(-l^2 / 2 (L_SCALE lmax)^2)


def synthetic_gram(m, lmax, l_scale, corr=3.0):
    """``D K D``: ``D_ll = exp(-l^2 / 2 L^2)``, ``K_jk = exp(-(j - k)^2 / 2 corr^2)`` (complex128)."""
    ell = np.arange(m, lmax + 1)
    d = np.exp(-0.5 * (ell / l_scale) ** 2)
    row = np.exp(-0.5 * (np.arange(len(ell)) / corr) ** 2)
    row[row < 1e-30] = 0.0  # no subnormal numbers: they slow LAPACK down (docs/performance.md) and mean nothing
    k = sla.toeplitz(row)
    return (d[:, None] * k * d[None, :]).astype(np.complex128)


def build_operators(lmax, eps, l_scale):
    """Block operators for every m with the paper's filters.

    Returns ``(ops, wall_seconds, cpu_seconds, flops)``: on a shared machine the process's CPU
    time shows how much of the wall time it actually ran.
    """
    grams = {}

    def one(m):
        g = grams.pop(m)
        return psf.block_operator(m, g, eps, filter_mask(m, lmax))

    ops, secs, cpu, flops = {}, 0.0, 0.0, 0.0
    batch = 2 * n_threads()
    for m0, m1 in m_blocks(lmax, batch):  # Grams made outside the timing, a few at a time
        ms = range(m0, m1)
        grams.update({m: synthetic_gram(m, lmax, l_scale) for m in ms})
        t0, c0 = time.perf_counter(), time.process_time()
        ops.update(zip(ms, psf.map_blocks(one, ms)))
        secs += time.perf_counter() - t0
        cpu += time.process_time() - c0
        flops += sum(8.0 * filter_mask(m, lmax).sum() ** 3 / 3 for m in ms)  # n^3/3 complex MACs
    return ops, secs, cpu, flops


def best_block_factor_gflops(n, eps, reps=3):
    """Best-of-``reps`` rate of ``n_threads()`` concurrent ``n x n`` Cholesky factors, GFLOP/s."""
    g = synthetic_gram(0, n - 1, 0.7 * n)
    keep = np.ones(n, bool)
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        psf.map_blocks(lambda _: psf.block_operator(2, g, eps, keep), range(n_threads()))
        best = min(best, time.perf_counter() - t0)
    return n_threads() * 8.0 * n**3 / 3 / best / 1e9


def _paper_projection(cycle_s, gain=0.15, n_peaks=256, noise_k=154.0, k_sigma=3.0, fwhm_arcmin=15.8,
                      freq_hz=73.152e6):
    """Cycles and time to the threshold for the paper's 73 MHz channel: a PROJECTION.

    Each cycle cleans at most ``n_peaks`` beams by a factor ``1 - gain``; a beam at brightness
    ``T`` needs ``ln(T / (k sigma)) / -ln(1 - gain)`` visits. ``T`` over the sky north of
    dec -30 is taken from mmflow's synthetic Galaxy-like sky at the channel's frequency.
    Two cases: the whole diffuse sky CLEANed (no high-pass split), and only compact sources
    after a smooth large-scale part is split off (source counts ``N(>S) = 2200 (S/1 Jy)^-1.1``
    over the 3 pi sr seen, VLSSr-like at 74 MHz, noise 598 mJy/beam).
    """
    nside = 64
    sky = healpy.alm2map(synthetic_sky_kelvin(freq_hz, 128, 2458000.5, nside=nside), nside, lmax=128)
    theta, _ = healpy.pix2ang(nside, np.arange(len(sky)))
    seen = (np.pi / 2 - theta) > np.deg2rad(-30)
    thr = k_sigma * noise_k
    visits = np.log(np.maximum(sky[seen], thr) / thr) / -np.log(1 - gain)
    beams_per_pixel = healpy.nside2pixarea(nside) / psf.gaussian_solid_angle(*np.deg2rad([fwhm_arcmin / 60] * 2))
    diffuse_cycles = float(visits.sum() * beams_per_pixel / n_peaks)
    s_thr = k_sigma * 0.598
    n_src = 2200 * s_thr ** -1.1
    # mean ln(S / S_thr) over a power law N(>S) ~ S^-1.1 is 1 / 1.1
    compact_cycles = float(n_src * (1 / 1.1) / -np.log(1 - gain) / n_peaks)
    return {"note": "projection from the measured cycle time, not a measured run",
            "cycle_s": cycle_s, "threshold_k": thr,
            "diffuse_sky_cycles": diffuse_cycles, "diffuse_sky_hours": diffuse_cycles * cycle_s / 3600,
            "compact_after_highpass_sources": n_src, "compact_after_highpass_cycles": compact_cycles,
            "compact_after_highpass_minutes": compact_cycles * cycle_s / 60}


def stage_cycle(ops, full_gram, dirty, table, mask, nside, lmax, m_block, workdir=None):
    """One major cycle as the ``clean`` stage runs it, timed part by part.

    The driver's :func:`clean.plan_cycle` (synthesis of the residual map, peak finding), then
    per m block of ``m_block`` m, on ``n_threads()`` threads as the cluster's workers would:
    read the block's stored Cholesky factors from a zarr array shaped as ``clean.zarr``'s
    ``chol_b`` (written once, before the timing), :func:`clean_stage.operators_from_factors`
    and :func:`clean_stage.cycle_block` (component alm, observe and subtract) -- the stage's
    own functions; ``full_gram(m)`` gives the Gram where a filter leaves a coupling (m = 1),
    as the stage reads it from ``normal.zarr``. The residual is checked against the in-memory :func:`clean.major_cycle`.
    The stage also checksums what it reads and records markers; that bookkeeping is not here.
    """
    blocks = m_blocks(lmax, m_block)
    keeps = {m: op.keep for m, op in ops.items()}
    tmp = tempfile.mkdtemp(prefix="mmflow-bench-clean-", dir=workdir)
    try:
        root = zarr.open_group(tmp, mode="w")
        t0 = time.perf_counter()
        for m0, m1 in blocks:
            chol = clean_stage.factors_of(ops, lmax, m0, m1)
            name = STORES.clean.chol(0, m0)  # the stage's array of channel 0
            root.create_array(name, shape=chol.shape, chunks=chol.shape, dtype=chol.dtype)[...] = chol
        store_s = time.perf_counter() - t0
        state = clean.CleanState(dirty)
        t0 = time.perf_counter()
        vecs, flux, peak, t = clean.plan_cycle(dirty, lmax, table, mask, nside)
        rows = np.zeros((len(flux), 4))
        rows[:, :3], rows[:, 3] = vecs, flux
        driver_s = time.perf_counter() - t0

        def one(block):
            m0, m1 = block
            t_a = time.perf_counter()
            chol = root[STORES.clean.chol(0, m0)][...]
            t_b = time.perf_counter()
            bops = clean_stage.operators_from_factors(chol, keeps, ops[m0].eps, lmax, m0, m1,
                                                      full_gram)
            t_c = time.perf_counter()
            new, tb = clean_stage.cycle_block(dirty[m_block_slice(lmax, m0, m1)], rows, bops, lmax, m0, m1)
            return new, {"read_factors": t_b - t_a, "operators": t_c - t_b, **tb}

        t0 = time.perf_counter()
        res = psf.map_blocks(one, blocks)
        blocks_s = time.perf_counter() - t0
        resid = np.concatenate([r[0] for r in res])
        direct, _ = clean.major_cycle(state, ops, lmax, table, mask, nside)
        err = float(np.abs(resid - direct.residual_alm).max() / np.abs(direct.residual_alm).max())
        sums = {k: float(sum(r[1][k] for r in res)) for k in res[0][1]}
        return {"seconds": driver_s + blocks_s, "driver_s": driver_s, "synthesis_s": t["synthesis"],
                "peaks_s": t["peaks"], "blocks_wall_s": blocks_s, "m_block": m_block, "n_blocks": len(blocks),
                "block_task_seconds_summed": {f"{k}_s": v for k, v in sums.items()},
                "observe_gflops": 2 * 8.0 * sum(op.keep.sum() ** 2 for op in ops.values()) / sums["observe"] / 1e9,
                "components": int(len(flux)), "first_peak_jy_sr": float(peak),
                "store_factors_once_s": store_s, "factors_gb_read_per_cycle": sum(
                    root[STORES.clean.chol(0, m0)].nbytes for m0, _ in blocks) / 1e9,
                "max_rel_difference_to_in_memory_cycle": err,
                "note": "threads run the m blocks as the stage's workers do: summed task seconds exceed the "
                        "blocks' wall time by about the thread count"}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def run(what="clean", quick=False):
    """Measure and return the figures (``mmflow bench clean``; ``python -m mmflow.bench.clean --paper-fwhm``
    for the paper-array Table-1 FWHM)."""
    lmax = 200 if quick else 1000
    m_block = TransferConfig.model_fields["m_block"].default
    nside = 2 * default_nside(lmax)
    eps = 1e-2
    out = {"machine": machine(), "threads": n_threads(), "lmax": lmax, "nside": nside,
           "gram": "synthetic D K D per m (see module docstring)", "m_block": m_block,
           "gemm_gflops": {"float64": gemm_gflops(np.float64), "float32": gemm_gflops(np.float32)}}
    ops, fac_s, fac_cpu, fac_flops = build_operators(lmax, eps, l_scale=L_SCALE * lmax)
    best = best_block_factor_gflops(lmax + 1, eps)
    out["factor"] = {"seconds": fac_s, "cpu_seconds": fac_cpu, "gflops": fac_flops / fac_s / 1e9,
                     "best_single_block_gflops": best,
                     "seconds_at_best_block_rate": fac_flops / best / 1e9,
                     "memory_gb": sum(op.nbytes for op in ops.values()) / 1e9}

    # PSF at one declination
    vec = radec_to_vec(0.0, np.deg2rad(45.0))
    t0 = time.perf_counter()
    a_ps = point_sources_alm(vec[None], [1.0], lmax)
    t1 = time.perf_counter()
    a_psf = psf.observe_alm(ops, a_ps, lmax)
    t2 = time.perf_counter()
    fit = psf.measure_psf(a_psf, lmax, vec)
    t3 = time.perf_counter()
    out["psf_one_dec"] = {"point_source_alm_s": t1 - t0, "observe_s": t2 - t1, "fit_s": t3 - t2,
                          "total_with_kept_factors_s": t3 - t0,
                          "total_with_factors_recomputed_s": t3 - t0 + fac_s,
                          "total_with_factors_recomputed_at_best_rate_s": t3 - t0 + fac_flops / best / 1e9,
                          "fwhm_major_arcmin": float(np.rad2deg(fit["major"]) * 60),
                          "fwhm_minor_arcmin": float(np.rad2deg(fit["minor"]) * 60)}

    # one CLEAN major cycle on a dirty map of a random sky plus 500 sources
    rng = np.random.default_rng(1)
    src = rng.normal(size=(500, 3))
    src /= np.linalg.norm(src, axis=1)[:, None]
    sky = band_limited_random_alm(lmax, seed=2) * 50 + point_sources_alm(src, rng.uniform(1, 100, 500), lmax)
    dirty = psf.observe_alm(ops, sky, lmax)
    table = psf.psf_table(ops, lmax, np.deg2rad([-30.0, 0.0, 45.0, 90.0]))
    table["peak"] = np.where(np.isfinite(table["peak"]), table["peak"], fit["value"])
    mask = clean.observed_mask(nside, np.deg2rad(-52.8))
    out["clean_major_cycle"] = stage_cycle(ops, lambda m: synthetic_gram(m, lmax, L_SCALE * lmax), dirty, table,
                                           mask, nside, lmax, m_block)
    cycle_s = out["clean_major_cycle"]["seconds"]
    out["paper_channel_projection"] = _paper_projection(cycle_s)
    out["gemm_gflops_at_end"] = {"float64": gemm_gflops(np.float64), "float32": gemm_gflops(np.float32)}
    return out


def paper_table1_fwhm(lmax=1000, freq_hz=73.152e6, target_fraction=0.512, decs_deg=(0.0, 45.0, 75.0),
                      layout=None):
    """Table 1's FWHM for the approximate paper array at 73.152 MHz (a measurement, slow).

    Builds the real Grams (``paper-2017`` layout, the bench's sin-elevation beam, float32
    transfer, complex64 Grams), picks eps so that the fraction of Gram eigenvalues above eps
    (kept coefficients, paper filters) is ``target_fraction`` (the paper's 0.512), and fits
    the PSF at each declination, streaming over m (one factor in memory per thread).
    ``layout`` replaces the paper's (a quick check of the path on a small array).
    The paper reports 18.6' x 15.1', 16.8' x 14.6', 16.6' x 16.1' at dec 0, +45, +75.
    """
    t0 = time.perf_counter()
    tel = Telescope(layout or ovro_lwa_layout("paper-2017"), BEAM, [freq_hz])
    nb = len(tel.antenna_pairs())
    acc = accumulate_normal_equations(tel, freq_hz, np.zeros((lmax + 1, 2, nb), np.complex64), lmax,
                                      dtype=np.float32)
    t_gram = time.perf_counter() - t0
    keep = {m: filter_mask(m, lmax) for m in acc.ms}

    def eig(m):
        g = acc.full_gram(m).astype(np.complex128)[np.ix_(keep[m], keep[m])]
        return np.linalg.eigvalsh(g) if len(g) else np.zeros(0)

    ev = np.concatenate(psf.map_blocks(eig, acc.ms))
    # complex64 Grams are good to ~1e-7 of their largest eigenvalue: eps stays above that
    eps = float(max(np.quantile(ev, 1 - target_fraction), 1e-6 * ev.max()))
    vecs = radec_to_vec(np.zeros(len(decs_deg)), np.deg2rad(decs_deg))
    a_ps = np.stack([point_sources_alm(v[None], [1.0], lmax) for v in vecs], axis=1)
    a_psf = np.zeros_like(a_ps)

    def observe(m):
        op = psf.block_operator(m, acc.full_gram(m).astype(np.complex128), eps, keep[m])
        sl = m_slice(lmax, m)
        a_psf[sl] = psf.observe_block(op, a_ps[sl])

    psf.map_blocks(observe, acc.ms)
    rows = {}
    for j, d in enumerate(decs_deg):
        fit = psf.measure_psf(a_psf[:, j], lmax, vecs[j])
        rows[f"{d:+.0f}"] = {"major_arcmin": float(np.rad2deg(fit["major"]) * 60),
                             "minor_arcmin": float(np.rad2deg(fit["minor"]) * 60),
                             "pa_deg": float(np.rad2deg(fit["pa"])), "peak": fit["value"]}
    paper = {"+0": (18.6, 15.1), "+45": (16.8, 14.6), "+75": (16.6, 16.1)}
    for k, r in rows.items():
        if k in paper:
            r["paper_arcmin"] = paper[k]
            r["ratio_major"] = r["major_arcmin"] / paper[k][0]
            r["ratio_minor"] = r["minor_arcmin"] / paper[k][1]
    return {"layout": "paper-2017 (approximation)" if layout is None else "given", "beam": type(BEAM).__name__,
            "baselines": nb, "lmax": lmax,
            "freq_mhz": freq_hz / 1e6, "eps": eps, "fraction_of_modes": float(np.mean(ev > eps)),
            "gram_seconds": t_gram, "total_seconds": time.perf_counter() - t0, "fwhm": rows}


if __name__ == "__main__":
    if "--paper-fwhm" in sys.argv:
        print(json.dumps(paper_table1_fwhm(lmax=200 if "--quick" in sys.argv else 1000), indent=1, default=float))
    else:
        print(json.dumps(run(quick="--quick" in sys.argv), indent=1, default=float))
