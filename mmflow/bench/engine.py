"""``mmflow bench transfer``, ``solve`` and ``simulate``: measured engine figures, printed as JSON.

Nothing here asserts a time; it measures, in one run, this machine's GEMM peak, the
transfer-matrix throughput (and the fraction of GEMM peak its Legendre step reaches), the
per-baseline healpy ``map2alm`` approach for comparison, Gram/Cholesky/solve rates, memory
scaling, and a projection for the reference paper's channel from the measured rates.
"""
from __future__ import annotations

import json
import resource
import subprocess
import sys
import time

import healpy
import numpy as np

from mmflow.conventions import enu_to_equatorial_matrix
from mmflow.imaging.solvers import tikhonov
from mmflow.machine import best_time, gemm_gflops, machine
from mmflow.mmode.normal import herk_upper
from mmflow.mmode.transfer import fringe_bandlimit, iter_transfer_blocks, make_grid
from mmflow.simulate.visibilities import healpix_points, simulate_drift_scan
from mmflow.sky.diffuse import synthetic_sky_kelvin
from mmflow.sky.units import kelvin_to_jy_per_sr
from mmflow.telescope import Telescope, ovro_lwa_layout
from mmflow.telescope.beams import SinElevationBeam

LAT = np.deg2rad(37.24)
BEAM = SinElevationBeam(1.5)


def full_lmax_baselines(lmax, nb, seed=0):
    """Baselines (wavelengths, sky frame) long enough that their per-baseline lmax is ``lmax``."""
    rng = np.random.default_rng(seed)
    kb = max(lmax - BEAM.lmax_hint, 1) / 1.1
    b = rng.normal(size=(nb, 3))
    b[:, 2] *= 0.02
    return b / np.linalg.norm(b, axis=1)[:, None] * kb / (2 * np.pi)


def transfer_rate(lmax, dtype, nb=64, chunks=3):
    """Baselines/s for baselines that need the full lmax (the worst case), steady state."""
    b = full_lmax_baselines(lmax, nb)
    grid = make_grid(LAT, BEAM, 50e6, lmax, fringe_bandlimit(np.linalg.norm(b, axis=1), BEAM.lmax_hint))
    for _ in iter_transfer_blocks(grid, b, dtype=dtype):  # warm: tables, workspace, FFT plans
        pass
    tim = {}
    t0 = time.perf_counter()
    for c in range(chunks):
        for _ in iter_transfer_blocks(grid, full_lmax_baselines(lmax, nb, seed=c + 1), dtype=dtype, timings=tim):
            pass
    el = time.perf_counter() - t0
    return {"lmax": lmax, "dtype": np.dtype(dtype).name, "baselines_per_s": nb * chunks / el,
            "grid": [grid.n_theta, grid.n_phi], "fourier_s_per_baseline": tim["fourier_s"] / (nb * chunks),
            "legendre_s_per_baseline": tim["legendre_s"] / (nb * chunks),
            "legendre_gflops": tim["legendre_flops"] / tim["legendre_s"] / 1e9}


def healpy_rate(lmax, nside, n=2):
    """The driftscan-style approach: per baseline, evaluate A e^{2 pi i b.r} on HEALPix, two map2alm."""
    vec = np.array(healpy.pix2vec(nside, np.arange(healpy.nside2npix(nside)))).T
    a = BEAM.power_enu(vec @ enu_to_equatorial_matrix(LAT), 50e6)
    bs = full_lmax_baselines(lmax, n)

    def one(b):
        f = a * np.exp(2j * np.pi * (vec @ b))
        healpy.map2alm(f.real, lmax=lmax, iter=0)
        healpy.map2alm(f.imag, lmax=lmax, iter=0)

    one(bs[0])
    t0 = time.perf_counter()
    for b in bs:
        one(b)
    return {"lmax": lmax, "nside": nside, "baselines_per_s": n / (time.perf_counter() - t0)}


def herk_rate(lmax, nb=64, dtype=np.complex64):
    rng = np.random.default_rng(0)
    blk = (rng.normal(size=(2 * nb, lmax + 1)) + 1j * rng.normal(size=(2 * nb, lmax + 1))).astype(dtype)
    c = herk_upper(blk)
    t = best_time(lambda: herk_upper(blk, c))
    t_gemm = best_time(lambda: blk.conj().T @ blk)
    flops = 4.0 * 2 * nb * (lmax + 1) ** 2  # complex herk: ~4 n k^2
    return {"lmax": lmax, "rows": 2 * nb, "dtype": np.dtype(dtype).name, "herk_gflops": flops / t / 1e9,
            "speedup_over_BhB": t_gemm / t}


def solve_rate(lmax, eps=0.01):
    """Cholesky factor + solve per m block; the total over all m from the L^3 model."""
    rng = np.random.default_rng(0)
    out = {}
    for n in sorted({min(lmax + 1, 128), min(lmax + 1, 512), lmax + 1}):
        x = rng.normal(size=(n + 16, n)) + 1j * rng.normal(size=(n + 16, n))
        g = x.conj().T @ x
        r = rng.normal(size=n) + 0j
        out[n] = best_time(lambda g=g, r=r: tikhonov(g, r, eps), reps=2)
    n_max = lmax + 1
    per_l3 = out[n_max] / n_max**3
    total = sum(per_l3 * (lmax - m + 1) ** 3 for m in range(lmax + 1))
    return {"lmax": lmax, "seconds_per_block": {str(k): v for k, v in out.items()}, "all_m_seconds": total}


def _paper_projection(rates, herk, solve):
    """The paper's channel (256 antennas, 32,896 baselines with autos, lmax 1000, 73.152 MHz)."""
    tel = Telescope(ovro_lwa_layout("paper-2017"), BEAM, [73.152e6])
    lmax_b = tel.baseline_lmax(73.152e6, 1000)
    # measured transfer cost per baseline at several lmax, interpolated in log-log
    ls = np.array([r["lmax"] for r in rates], float)
    ts = np.array([1.0 / r["baselines_per_s"] for r in rates])
    slope = np.polyfit(np.log(ls), np.log(ts), 1)
    t_bl = np.exp(np.polyval(slope, np.log(np.maximum(lmax_b, ls.min()))))
    transfer_s = float(t_bl.sum())
    # Gram: each baseline adds 2 rows to blocks m <= lmax_b with lmax_b - m + 1 columns
    herk_flops = float(sum(4.0 * 2 * ((lb - np.arange(lb + 1) + 1) ** 2).sum() for lb in lmax_b))
    gram_s = herk_flops / (herk["herk_gflops"] * 1e9)
    return {"baselines": int(len(lmax_b)), "lmax": 1000, "freq_mhz": 73.152,
            "median_baseline_lmax": float(np.median(lmax_b)), "baselines_at_lmax_1000": int(np.sum(lmax_b >= 1000)),
            "transfer_s": transfer_s, "gram_s": gram_s, "solve_s": solve["all_m_seconds"],
            "total_minutes": (transfer_s + gram_s + solve["all_m_seconds"]) / 60.0,
            "model": f"t_baseline ~ lmax_b^{slope[0]:.2f} fitted to the measured float32 rates"}


def memory_scaling(lmax=160, sizes=(64, 128, 256)):
    """Peak RSS of the streaming normal equations for growing numbers of baselines (subprocesses).

    Uses the longest baselines of the ``paper-2017`` layout at 73.152 MHz (every chunk at the
    full lmax) in float32. Read from ``VmHWM`` (the high-water mark of the new address space):
    ``ru_maxrss`` survives fork+exec on Linux and would report the parent's peak.
    """
    code = ("import numpy as np, sys\n"
            "from mmflow.telescope import Telescope, ovro_lwa_layout\n"
            "from mmflow.telescope.beams import SinElevationBeam\n"
            "from mmflow.mmode.engine import accumulate_normal_equations\n"
            "n=int(sys.argv[1]); L=int(sys.argv[2]); f=73.152e6\n"
            "tel=Telescope(ovro_lwa_layout('paper-2017'), SinElevationBeam(1.5), [f])\n"
            "p=tel.antenna_pairs(); tel.pairs=p[np.argsort(np.linalg.norm(tel.baselines_enu(p),axis=1))[::-1][:n]]\n"
            "mm=np.zeros((L+1,2,n),complex)\n"
            "accumulate_normal_equations(tel, f, mm, L, chunk_size=64, dtype=np.float32)\n"
            "print([l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM')][0])\n")
    out = {}
    for n in sizes:
        res = subprocess.run([sys.executable, "-c", code, str(n), str(lmax)], capture_output=True, text=True,
                             check=True)
        out[str(n)] = int(res.stdout.strip().splitlines()[-1]) / 1024.0
    return {"lmax": lmax, "dtype": "float32", "peak_rss_mb_by_n_baselines": out}


def simulate_rate(n_ant=64, nside=64, n_time=6628, freq_hz=50e6):
    """The independent simulator: ``n_ant`` OVRO-LWA core stands, a HEALPix diffuse sky, one day."""
    tel = Telescope(ovro_lwa_layout("core", max_antennas=n_ant), BEAM, [freq_hz])
    alm = synthetic_sky_kelvin(freq_hz, 3 * nside - 1, 2457802.0)
    sky = healpix_points(kelvin_to_jy_per_sr(healpy.alm2map(alm, nside), freq_hz))
    lst = 2 * np.pi * np.arange(n_time) / 6628
    t0 = time.perf_counter()
    vis = simulate_drift_scan(tel, freq_hz, lst, sky, dtype=np.complex64)
    el = time.perf_counter() - t0
    return {"n_ant": n_ant, "n_baselines": int(vis.shape[1]), "nside": nside, "integrations": n_time,
            "seconds": el, "seconds_per_sidereal_day": el * 6628 / n_time}


def run(what, quick=False):
    res = {"machine": machine()}
    if what == "transfer":
        res["sgemm_gflops"] = gemm_gflops(np.float32)
        res["dgemm_gflops"] = gemm_gflops(np.float64)
        lmaxes = (128, 256) if quick else (256, 512, 1000)
        res["transfer"] = [transfer_rate(L, dt) for L in lmaxes for dt in (np.float32, np.float64)]
        for r in res["transfer"]:
            peak = res["sgemm_gflops"] if r["dtype"] == "float32" else res["dgemm_gflops"]
            r["legendre_fraction_of_gemm_peak"] = r["legendre_gflops"] / peak
        hl, hn = (256, 256) if quick else (1000, 1024)
        res["healpy_map2alm"] = healpy_rate(hl, hn, n=1 if quick else 2)
        ours = max(r["baselines_per_s"] for r in res["transfer"] if r["lmax"] == hl and r["dtype"] == "float32")
        res["speedup_over_healpy"] = ours / res["healpy_map2alm"]["baselines_per_s"]
    elif what == "simulate":
        res["simulate"] = simulate_rate(n_time=256 if quick else 6628)
    elif what == "solve":
        lmax = 256 if quick else 1000
        res["herk"] = herk_rate(lmax)
        res["solve"] = solve_rate(lmax)
        rates = [transfer_rate(L, np.float32) for L in ((64, 128, 256) if quick else (128, 256, 512, 1000))]
        res["transfer_float32"] = rates
        res["paper_channel_projection"] = _paper_projection(rates, res["herk"], res["solve"])
        res["memory"] = memory_scaling(96 if quick else 1000, (32, 64, 128) if quick else (64, 128, 256))
    res["peak_rss_mb_this_process"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return res


if __name__ == "__main__":
    print(json.dumps(run(sys.argv[1], quick="--quick" in sys.argv), indent=2))
