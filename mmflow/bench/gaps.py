"""``mmflow bench gaps``: cost of the least-squares m-modes (:mod:`mmflow.mmode.gapfill`).

One sidereal day at the OVRO-LWA cadence (N = 6628 bins); per band limit ``M_b`` (100, 500,
1000) and flag pattern (none, 5 % of bins at random, 20 % in four blocks) a chunk of
baselines holding random band-limited drift scans is fitted, noiseless (``sigma2`` not given) and
with noise at 100 per bin (``sigma2`` given: the gaps' pseudo-observations). The JSON gives ms per baseline,
CG iterations (median, max), how many converged to ``tol``, the error against the true
m-modes and that of zero-filling, beside the plain FFT transform's ms per baseline and the
FFT rate of this machine measured in the same run (the reference peak).
"""
from __future__ import annotations

import json
import sys
import time
import tracemalloc

import numpy as np
import scipy.fft

from mmflow.machine import machine
from mmflow.mmode.gapfill import chunk_mmodes, lsq_mmodes, relative_rms
from mmflow.mmode.transform import mmode_transform

N_BINS = 6628


def _flags(pattern, n, nb, rng):
    w = np.ones((n, nb))
    if pattern == "random5":
        w[rng.random((n, nb)) < 0.05] = 0
    elif pattern == "blocks20":
        seg, length = n // 4, int(round(0.05 * n))
        for b in range(nb):
            for k in range(4):
                s = k * seg + rng.integers(0, seg - length)
                w[s:s + length, b] = 0
    return w


def _scans(band, nb, rng):
    """Random m-modes with |m| <= band (mmflow layout) and their drift scans on the bin grid."""
    x = rng.normal(size=(2 * band + 1, nb)) + 1j * rng.normal(size=(2 * band + 1, nb))
    grid = np.zeros((N_BINS, nb), complex)
    grid[np.arange(-band, band + 1) % N_BINS] = x
    vis = np.fft.ifft(grid, axis=0) * N_BINS
    return vis, np.fft.fft(vis, axis=0) / N_BINS


def fft_rate(n=N_BINS, nb=64, reps=5):
    """Complex FFTs of length ``n`` per second (batched over ``nb`` columns), best of ``reps``."""
    a = np.random.default_rng(0).normal(size=(nb, n)) + 0j
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        scipy.fft.fft(a, axis=-1)
        best = min(best, time.perf_counter() - t0)
    return nb / best


def case(band, pattern, nb, tol=1e-10, snr=None, seed=0):
    """One fit; ``snr``: signal-to-noise ratio per bin of added noise, passed as ``sigma2`` (None: noiseless)."""
    rng = np.random.default_rng(seed)
    vis, _ = _scans(band, nb, rng)
    w = _flags(pattern, N_BINS, nb, rng)
    ref = mmode_transform(vis, band)
    s2 = None
    if snr is not None:
        s2 = np.mean(np.abs(vis) ** 2, axis=0) / snr
        vis = vis + np.sqrt(s2 / 2) * (rng.normal(size=vis.shape) + 1j * rng.normal(size=vis.shape))
    t0 = time.perf_counter()
    res = lsq_mmodes(vis, w, band, sigma2=s2, tol=tol)
    el = time.perf_counter() - t0
    t0 = time.perf_counter()
    zf = mmode_transform(np.where(w > 0, vis, 0), band)
    el_plain = time.perf_counter() - t0
    return {"band_limit": band, "flags": pattern, "tol": tol, "snr_per_bin": snr, "baselines": nb,
            "ms_per_baseline": 1e3 * el / nb, "plain_transform_ms_per_baseline": 1e3 * el_plain / nb,
            "iterations_median": float(np.median(res.iterations)), "iterations_max": int(res.iterations.max()),
            "converged": int(res.converged.sum()),
            "lsq_relative_rms_median": float(np.median(relative_rms(res.mmodes, ref))),
            "zero_filled_relative_rms_median": float(np.median(relative_rms(zf, ref)))}


def run(what="gaps", quick=False):
    nb = 4 if quick else 16
    bands = (100, 500) if quick else (100, 500, 1000)
    res = {"machine": machine(), "n_bins": N_BINS,
           "fft_per_s_length_n_bins": fft_rate(),
           "cases": [case(b, p, nb) for b in bands for p in ("none", "random5", "blocks20")]}
    res["cases"] += [case(b, p, nb, snr=100.0) for b in bands for p in ("random5", "blocks20")]
    if not quick:
        res["cases"] += [case(b, "blocks20", nb, tol=1e-6) for b in bands]
    return res


if __name__ == "__main__":
    print(json.dumps(run("gaps", quick="--quick" in sys.argv), indent=2))


def traced_fit_bytes(n_bins, k_max, mmax, n_bl, rng, splits=("full", "even", "odd")):
    """Peak bytes ``tracemalloc`` reads while :func:`mmflow.mmode.gapfill.chunk_mmodes` fits random data of
    ``n_bins`` bins and ``n_bl`` baselines up to band ``k_max`` (``mmax``: the m-modes it returns), with a gap of
    8 % of the bins so that the least-squares fit runs, not the plain transform: what
    :func:`mmflow.workflow.stages.mmodes.cost.fit_bytes` counts (``benchmarks/mmode_fit_memory.py``)."""
    binned = rng.normal(size=(n_bins, n_bl)) + 1j * rng.normal(size=(n_bins, n_bl))
    weight = np.ones((n_bins, n_bl))
    weight[n_bins // 5:n_bins // 5 + n_bins // 12] = 0
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        chunk_mmodes(binned, weight, mmax, None, np.full(n_bl, k_max), list(splits), np.ones(n_bl), 0.5, "drop")
        return tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
