"""``mmflow bench transfer --stokes IQUV``: full-Stokes transfer + Gram against Stokes I, one run.

For the same baselines, frequency and lmax (float32, the workflow's precision), Q, U and V to the
default band limit ``imaging.stokes_lmax`` (:data:`mmflow.conventions.STOKES_LMAX_DEFAULT`, or
lmax if lower), the seconds of

* Stokes I: the engine's ring-FFT + per-m GEMM transfer blocks and the ``herk`` of each m's
  Gram (:func:`mmflow.mmode.engine.accumulate_normal_equations`, every m's Gram kept);
* full Stokes: the same structure for the four correlations against T, E, B, V
  (:func:`mmflow.mmode.polarised_transfer.polarised_pass`: four ring FFTs per correlation, six
  real GEMMs per m and correlation; above the polarised band limit the I kernels alone and two) and one
  ``herk`` per m of the ``(L_m + 3 P_m)^2`` Gram (:func:`mmflow.mmode.normal.herk_into`) into one Gram
  per thread (the stokes stage holds a block of m's Grams at a time; the benchmark does each update's
  work without keeping the sum);

(Stokes I the best of three calls, full Stokes one pass of minutes) and
their ratio, and the ratio of the two paths' flop counts (Legendre GEMMs + ``herk``), beside the
SGEMM peak measured in the same run (``full_stokes_fraction_of_sgemm_peak``; ``time_ratio_over_flop_ratio``,
the time ratio over the flop ratio). With every Stokes parameter to lmax full Stokes solves for 4x the
unknowns from 4x the rows, so its Gram alone is ~64x the Stokes-I one (4 x 4^2); Q, U, V to l = 256 at
lmax 1000 make it ~7x (docs/stokes.md).
"""
from __future__ import annotations

import threading
import time

import numpy as np

from mmflow.conventions import STOKES_LMAX_DEFAULT, stokes_sizes
from mmflow.machine import best_time, gemm_gflops, machine
from mmflow.mmode.engine import accumulate_normal_equations
from mmflow.mmode.normal import herk_into
from mmflow.mmode.polarised import CORRELATIONS, make_polarised_grid
from mmflow.mmode.polarised_transfer import (FourierBuffers, active_rings, baselines_per_pass, legendre_rows,
                                            polarised_pass)
from mmflow.mmode.transfer import baselines_in_wavelengths, fringe_bandlimit
from mmflow.telescope import Telescope, ovro_lwa_layout
from mmflow.telescope.jones import ShortDipoleJones

FREQ_HZ = 73.152e6


def _telescope(lmax, n_bl, seed=0):
    """The paper-2017 layout and ``n_bl`` of its cross baselines (fixed seed) whose fringes need about
    ``lmax`` (``0.8 lmax <= 2 pi |b| <= lmax``, or the ``n_bl`` nearest ``0.9 lmax`` where too few)."""
    jones = ShortDipoleJones(horizon_taper=3.0)
    tel = Telescope(ovro_lwa_layout("paper-2017"), jones.power_beam(), [FREQ_HZ], include_autos=False)
    pairs = tel.antenna_pairs()
    kb = 2 * np.pi * np.linalg.norm(baselines_in_wavelengths(tel, pairs, FREQ_HZ), axis=1)
    pool = np.flatnonzero((kb >= 0.8 * lmax) & (kb <= lmax))
    if len(pool) < n_bl:
        pool = np.argsort(np.abs(kb - 0.9 * lmax))[:n_bl]
    tel.pairs = pairs[np.sort(np.random.default_rng(seed).choice(pool, n_bl, replace=False))]
    return tel, jones


def _full_stokes(tel, jones, lmax, lmax_p, timings):
    """Seconds of the full-Stokes transfer + per-m ``herk`` (float32), Q, U, V to ``lmax_p``, and its flop
    count (Legendre GEMMs and ``herk``, as :func:`mmflow.imaging.polarised.accumulate_polarised_normal`
    forms them)."""
    b = baselines_in_wavelengths(tel, tel.pairs, FREQ_HZ)
    local = threading.local()
    nc = len(CORRELATIONS)
    flops = [0.0]

    def consume(m, block):
        n_l, cols = block.shape[0], block.shape[-1]
        n_p = stokes_sizes(m, lmax, lmax_p)[1]
        if not hasattr(local, "gram"):
            local.gram = np.zeros((sum(stokes_sizes(0, lmax, lmax_p) * np.array([1, 3])),) * 2, np.complex64,
                                  order="F")
        xs = np.concatenate([block[:, 0]] + [block[:n_p, x] for x in (1, 2, 3)]).reshape(n_l + 3 * n_p, nc * cols)
        herk_into(local.gram, xs, nc * cols, n_l + 3 * n_p, nc * cols)
        flops[0] += 4.0 * nc * cols * (n_l + 3 * n_p) ** 2  # herk: 8 flops per complex product, half the matrix

    t0 = time.perf_counter()
    grid = make_polarised_grid(tel.lat_rad, jones, FREQ_HZ, lmax,
                               fringe_bandlimit(np.linalg.norm(b, axis=1), jones.lmax_hint))
    t_grid = time.perf_counter() - t0
    t0 = time.perf_counter()
    step = baselines_per_pass(grid, nc, np.dtype(np.complex64).itemsize, lmax_pol=lmax_p)
    buffers = FourierBuffers()
    for s0 in range(0, len(b), step):  # as accumulate_polarised_normal chunks its baselines
        polarised_pass(grid, b[s0:s0 + step], consume, dtype=np.float32, timings=timings, lmax_pol=lmax_p,
                       buffers=buffers)
    n_act = len(active_rings(grid))

    # Legendre: rows x (corr x cols) complex columns against n_act rings, 2 real flops per product
    leg = sum(2.0 * legendre_rows(*stokes_sizes(m, lmax, lmax_p)) * n_act * nc * (len(b) if m == 0 else 2 * len(b)) * 2
              for m in range(lmax + 1))
    return time.perf_counter() - t0, t_grid, flops[0] + leg


def compare(lmax, n_bl, lmax_p=None):
    """Seconds of Stokes-I and full-Stokes transfer + Gram for ``n_bl`` baselines at ``lmax`` (float32), Q, U
    and V to ``lmax_p`` (default ``min(lmax, STOKES_LMAX_DEFAULT)``)."""
    lmax_p = min(lmax, STOKES_LMAX_DEFAULT if lmax_p is None else lmax_p)
    tel, jones = _telescope(lmax, n_bl)
    mm = np.zeros((lmax + 1, 2, n_bl), np.complex128)
    tim_i = {}  # the warm-up call (tables, workspace) counts the Legendre flops
    accumulate_normal_equations(tel, FREQ_HZ, mm, lmax, dtype=np.float32, per_baseline_lmax=False, timings=tim_i)
    # best of three: Stokes I is short, and one reading of a few seconds swings with the VM
    t_i = best_time(lambda: accumulate_normal_equations(tel, FREQ_HZ, mm, lmax, dtype=np.float32,
                                                        per_baseline_lmax=False))
    flops_i = tim_i.get("legendre_flops", 0.0) + sum(4.0 * (n_bl if m == 0 else 2 * n_bl) * (lmax - m + 1) ** 2
                                                      for m in range(lmax + 1))
    tim = {}
    t_iquv, t_grid, flops_iquv = _full_stokes(tel, jones, lmax, lmax_p, tim)
    return {"lmax": lmax, "stokes_lmax": lmax_p, "baselines": n_bl, "stokes_i_s": t_i, "full_stokes_s": t_iquv,
            "full_over_i": t_iquv / t_i, "flops_full_over_i": flops_iquv / flops_i,
            "time_ratio_over_flop_ratio": (t_iquv / t_i) / (flops_iquv / flops_i),
            "full_stokes_flops": flops_iquv, "stokes_i_flops": flops_i,
            "full_stokes_gflops": flops_iquv / t_iquv / 1e9, "stokes_i_gflops": flops_i / t_i / 1e9,
            "full_stokes_s_per_baseline": t_iquv / n_bl, "full_stokes_grid_s": t_grid,
            "full_stokes_phases_s": {k: round(v, 3) for k, v in tim.items() if k.endswith("_s")},
            # the ring stage (kernel x fringe products and their FFTs) is not in the flop count
            "ring_stage_fraction_of_full_stokes": tim.get("fourier_s", 0.0) / t_iquv,
            "full_stokes_gflops_outside_ring_stage": flops_iquv / max(t_iquv - tim.get("fourier_s", 0.0), 1e-9) / 1e9}


def run(what, quick=False, **options):
    res = {"machine": machine(), "sgemm_gflops": gemm_gflops(np.float32)}
    sizes = ((32, 8), (64, 8)) if quick else ((128, 64), (1000, 64))
    res["stokes_iquv_vs_i"] = [compare(lmax, n) for lmax, n in sizes]
    res["sgemm_gflops_after"] = gemm_gflops(np.float32)
    peak = max(res["sgemm_gflops"], res["sgemm_gflops_after"])
    for r in res["stokes_iquv_vs_i"]:
        r["full_stokes_fraction_of_sgemm_peak"] = r["full_stokes_gflops"] / peak
        r["outside_ring_stage_fraction_of_sgemm_peak"] = r["full_stokes_gflops_outside_ring_stage"] / peak
    return res
