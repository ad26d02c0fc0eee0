"""``mmflow bench table1``: the paper's Table-1 resolution on the paper's array, measured.

The paper's array (``ovro_lwa_layout("paper-2017")``, 256 stands) at 73.152 MHz and lmax
1000: the normal equations through the engine (unit noise weights), ``eps`` chosen by
bisection so that the fraction of singular values of B above ``sqrt(eps)`` (eigenvalues of
``G_m`` above ``eps``, counted exactly by inertia, :func:`count_eigenvalues_above`) over all m
is the paper's 0.512, then the PSF at dec +45 (with the paper's m-filters) and its FWHM by an
elliptical fit to the half-power region (:func:`mmflow.imaging.psf.measure_psf`), beside the
paper's 16.8' x 14.6'. The layout and beam (``sin_elevation`` 1.5) approximate the real
instrument: the ratio is reported, nothing is tuned to it. ``--quick`` runs lmax 200 on the
``core`` array (a smoke run).
"""
from __future__ import annotations

import sys
import time

import numpy as np

from mmflow.bench.channel import telescope_for
from mmflow.conventions import radec_to_vec
from mmflow.imaging.psf import block_operators, map_blocks, measure_psf, psf_alm
from mmflow.imaging.solvers import count_eigenvalues_above
from mmflow.mmode.engine import accumulate_normal_equations

PAPER_FWHM_ARCMIN = (16.8, 14.6)
PAPER_FRACTION = 0.512


def _log(msg):
    print(f"[bench table1 {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _fraction(acc, eps, ms):
    counts = map_blocks(lambda m: (count_eigenvalues_above(acc.full_gram(m), eps), acc.lmax - m + 1), ms)
    return sum(c for c, _ in counts) / sum(n for _, n in counts)


def choose_eps(acc, target, ms, steps=20):
    """Bisection in ``log eps`` for the fraction ``target`` over the blocks ``ms``."""
    diag = max(float(np.abs(np.diagonal(acc.full_gram(m))).max()) for m in ms[:4])
    lo, hi = diag * 1e-14, diag * 10
    for _ in range(steps):
        mid = np.sqrt(lo * hi)
        if _fraction(acc, mid, ms) > target:
            lo = mid
        else:
            hi = mid
        if hi / lo < 1.02:
            break
    return float(np.sqrt(lo * hi))


def run(what="table1", quick=False):
    layout, f, lmax = ("core", 40e6, 200) if quick else ("paper-2017", 73.152e6, 1000)
    tel = telescope_for(layout, f)
    nbl = len(tel.antenna_pairs())
    t0 = time.perf_counter()
    _log(f"normal equations: {layout}, {nbl} baselines, {f / 1e6:.3f} MHz, lmax {lmax}")
    acc = accumulate_normal_equations(tel, f, np.zeros((lmax + 1, 2, nbl), np.complex64), lmax, dtype=np.float32)
    t_acc = time.perf_counter() - t0
    _log(f"normal equations in {t_acc:.0f} s; choosing eps for fraction {PAPER_FRACTION}")
    coarse = list(range(0, lmax + 1, 5))
    eps = choose_eps(acc, PAPER_FRACTION, coarse)
    frac = _fraction(acc, eps, list(range(lmax + 1)))
    t_eps = time.perf_counter() - t0 - t_acc
    _log(f"eps {eps:.4g}: fraction {frac:.4f} over all m ({t_eps:.0f} s); PSF at dec +45")
    ops = block_operators(acc, eps)
    vec = radec_to_vec(0.0, np.deg2rad(45.0))
    beam = measure_psf(psf_alm(ops, lmax, vec), lmax, vec)
    major, minor = (float(np.rad2deg(beam[k]) * 60) for k in ("major", "minor"))
    out = {"layout": layout, "freq_mhz": f / 1e6, "lmax": lmax, "baselines": nbl, "beam": "sin_elevation 1.5",
           "eps": eps, "fraction_singular_values_above_sqrt_eps": frac,
           "fwhm_dec45_arcmin": [major, minor], "position_angle_deg": float(np.rad2deg(beam.get("pa", np.nan))),
           "seconds": {"normal_equations": round(t_acc, 1), "eps": round(t_eps, 1),
                       "psf": round(time.perf_counter() - t0 - t_acc - t_eps, 1)}}
    if not quick:
        out["paper_fwhm_arcmin"] = list(PAPER_FWHM_ARCMIN)
        out["ratio_to_paper"] = [major / PAPER_FWHM_ARCMIN[0], minor / PAPER_FWHM_ARCMIN[1]]
    return out
