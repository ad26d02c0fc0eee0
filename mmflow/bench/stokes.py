"""``mmflow bench transfer --stokes IQUV``: full-Stokes transfer + Gram against Stokes I, one run.

For the same baselines, frequency and lmax, the seconds of

* Stokes I: the engine's ring-FFT + per-m GEMM transfer blocks and the ``herk`` Gram
  (:func:`mmflow.mmode.engine.accumulate_normal_equations`, float32, the workflow's path);
* full Stokes: the reference kernels (:func:`mmflow.imaging.polarised.accumulate_polarised_normal`:
  six spherical-harmonic transforms per baseline and correlation, the Gram over ``4 (lmax - m + 1)``
  unknowns per m, complex128),

and their ratio, beside the SGEMM peak measured in the same run. Issue 22's target is a ratio
<= 5 at lmax 1000; the reference kernels hold a channel's whole Gram (~170 GB at lmax 1000), so
the ratio is measured at the lmax they reach and reported as such (docs/stokes.md).
"""
from __future__ import annotations

import time

import numpy as np

from mmflow.imaging.polarised import accumulate_polarised_normal
from mmflow.machine import gemm_gflops, machine
from mmflow.mmode.engine import accumulate_normal_equations
from mmflow.mmode.polarised import make_polarised_grid
from mmflow.mmode.transfer import baselines_in_wavelengths, fringe_bandlimit
from mmflow.telescope import Telescope, ovro_lwa_layout
from mmflow.telescope.jones import ShortDipoleJones

FREQ_HZ = 40e6


def _telescope(n_bl, seed=0):
    """OVRO-LWA core stands within 60 m and ``n_bl`` of their cross baselines (fixed seed)."""
    jones = ShortDipoleJones(horizon_taper=3.0)
    tel = Telescope(ovro_lwa_layout("core", radius_m=60.0), jones.power_beam(), [FREQ_HZ], include_autos=False)
    pairs = tel.antenna_pairs()
    tel.pairs = pairs[np.sort(np.random.default_rng(seed).choice(len(pairs), n_bl, replace=False))]
    return tel, jones


def compare(lmax, n_bl):
    """Seconds of Stokes-I and full-Stokes transfer + Gram for ``n_bl`` baselines at ``lmax``."""
    tel, jones = _telescope(n_bl)
    mm = np.zeros((lmax + 1, 2, n_bl), np.complex128)
    accumulate_normal_equations(tel, FREQ_HZ, mm, lmax, dtype=np.float32, per_baseline_lmax=False)  # warm: tables
    t0 = time.perf_counter()
    accumulate_normal_equations(tel, FREQ_HZ, mm, lmax, dtype=np.float32, per_baseline_lmax=False)
    t_i = time.perf_counter() - t0
    b = baselines_in_wavelengths(tel, tel.pairs, FREQ_HZ)
    t0 = time.perf_counter()
    grid = make_polarised_grid(tel.lat_rad, jones, FREQ_HZ, lmax, fringe_bandlimit(np.linalg.norm(b, axis=1),
                                                                                    jones.lmax_hint))
    accumulate_polarised_normal(grid, b)
    t_iquv = time.perf_counter() - t0
    return {"lmax": lmax, "baselines": n_bl, "stokes_i_s": t_i, "full_stokes_s": t_iquv,
            "full_over_i": t_iquv / t_i, "full_stokes_s_per_baseline": t_iquv / n_bl}


def run(what, quick=False, **options):
    res = {"machine": machine(), "sgemm_gflops": gemm_gflops(np.float32)}
    sizes = ((32, 16), (64, 16)) if quick else ((64, 32), (128, 32), (256, 16))
    res["stokes_iquv_vs_i"] = [compare(lmax, n) for lmax, n in sizes]
    res["lmax_1000"] = ("not measured: the reference kernels hold the whole Gram over 4 (lmax - m + 1) unknowns "
                        "per m (~170 GB at lmax 1000); the fast path is not built (docs/stokes.md)")
    res["sgemm_gflops_after"] = gemm_gflops(np.float32)
    return res
