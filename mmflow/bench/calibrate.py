"""``mmflow bench calibrate``: Stefcal and peeling throughput at the paper's scale, as JSON.

256 antennas (the ``paper-2017`` layout), one channel, complex64 data. Measured in one run:
this machine's SGEMM peak and a memory-bandwidth peak (numpy copy), one Stefcal sweep (the
numba kernel and the plain numpy implementation of the same update, and their ratio), a full
Stefcal solve, and peeling 8 sources with 5 passes per integration (cold start from unit DD
gains, the stage's default, and warm start from the previous integration), projected to the
paper's 28 h day (7,756 integrations) and its 8 channels; the calibration demo's recipe at
that scale (2 peeled, 2 subtracted, 7 modelled sources); and the gain solve of one 22-min track
with Cyg A and Cas A screened against the same solve on the catalogue models; the terrestrial stage's
sky loss of one channel's two templates (its driver step, ``terrestrial.amplitudes: auto``). Nothing here
asserts a time.
"""
from __future__ import annotations

import json
import os
import sys
import time
from contextlib import contextmanager

import numpy as np

from mmflow.environ import restored_environ
from mmflow.calibrate.coherency import source_coherencies, source_vector_date
from mmflow.calibrate.dd_screen import screen_basis, screen_gains, sky_tangents_enu
from mmflow.calibrate.peel import MODEL, PEEL, SUBTRACT, add_component, peel_dense
from mmflow.calibrate.screened_gains import solve_gains_screened
from mmflow.calibrate.stefcal import solve_gains, stefcal, sweep, sweep_numpy
from mmflow.calibrate.terrestrial import LOSS_BASELINES, TRACK_POINTS, template_sky_loss
from mmflow.telescope.beams import SinElevationBeam
from mmflow.machine import best_time, gemm_gflops, machine
from mmflow.simulate.corrupt import gain_products
from mmflow.sky.sources import get_sources
from mmflow.telescope import ovro_lwa_layout
from mmflow.threads import n_threads, single_threaded_blas, usable_cores
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.context import build_telescope
from mmflow.workflow.stages.peel.solve import peel_names, peel_solve, solve_dtype
from mmflow.conventions import SPEED_OF_LIGHT

N_DAY = 7756  # 13 s integrations in the paper's 28 h
N_CHANNELS_PAPER = 8
FREQ = 60e6


def _layout(n_ant):
    try:
        enu = ovro_lwa_layout("paper-2017").enu[:n_ant]
        if len(enu) == n_ant:
            return enu, "paper-2017"
    except Exception:  # noqa: BLE001 -- the benchmark still runs on a synthetic array
        pass
    rng = np.random.default_rng(0)
    r = 200 * np.sqrt(rng.uniform(size=n_ant))
    a = rng.uniform(0, 2 * np.pi, n_ant)
    return np.stack([r * np.sin(a), r * np.cos(a), np.zeros(n_ant)], 1), "random 200 m disc"


def _problem(n_ant, n_int, n_src, rng):
    """Point-source coherencies, DD gains (refraction + scintillation), data with noise."""
    enu, name = _layout(n_ant)
    lam = SPEED_OF_LIGHT / FREQ
    d = rng.normal(size=(n_src, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.7
    d /= np.linalg.norm(d, axis=1)[:, None]
    flux = np.array([16000, 14000, 2500, 1800, 400, 350, 250, 200, 150, 100, 80][:n_src], float)
    z = np.exp(2j * np.pi * enu @ d.T / lam)  # (N, n_src)
    M = (flux[:, None, None] * np.conj(z.T)[:, :, None] * z.T[:, None, :]).astype(np.complex64)
    M = np.broadcast_to(M[:, None], (n_src, n_int, n_ant, n_ant))
    # refraction: 20' at 36.5 MHz scaling nu^-2 is 7.4' at 60 MHz; 3' rms per axis
    shift = np.deg2rad(3 / 60) * rng.normal(size=(n_src, n_int, 3))
    g = np.exp(-2j * np.pi * np.einsum("stk,ik->sti", shift, enu) / lam)
    g *= np.sqrt(1 + 0.1 * rng.normal(size=(n_src, n_int)))[..., None]
    V = np.einsum("sti,stij,stj->tij", g, M, np.conj(g))
    noise = 50 * (rng.normal(size=V.shape) + 1j * rng.normal(size=V.shape))
    V = (V + np.triu(noise, 1) + np.conj(np.swapaxes(np.triu(noise, 1), 1, 2))).astype(np.complex64)
    W = np.ones((n_int, n_ant, n_ant), np.float32)
    W[:, np.arange(n_ant), np.arange(n_ant)] = 0
    return V, np.ascontiguousarray(M), W, g, name


def memory_bandwidth_gbs(n=2**25):
    a = np.ones(n, np.float32)
    b = np.empty_like(a)
    np.copyto(b, a)
    return 2 * a.nbytes / best_time(lambda: np.copyto(b, a), 5) / 1e9


def stefcal_rates(n_ant=256, n_int=16, reps=5, rng=None):
    rng = rng or np.random.default_rng(1)
    V, M, W, g, _ = _problem(n_ant, n_int, 1, rng)
    Vk, Mk, Wk = V[:, None], M[0][:, None], W[:, None]
    g0 = np.ones((n_int, n_ant), complex)
    sweep(Vk, Mk, Wk, g0)  # compile
    t_numba = best_time(lambda: sweep(Vk, Mk, Wk, g0), reps)
    t_numpy = best_time(lambda: sweep_numpy(Vk, Mk, Wk, g0), max(1, reps // 2))
    diff = np.abs(sweep(Vk, Mk, Wk, g0) - sweep_numpy(Vk, Mk, Wk, g0)).max()
    t0 = time.perf_counter()
    res = stefcal(Vk, Mk, Wk, tol=1e-5, max_iter=100, diagnostics=False)
    t_solve = time.perf_counter() - t0
    elements = n_int * n_ant * n_ant
    return {"n_ant": n_ant, "integrations_per_call": n_int, "dtype": "complex64",
            "ms_per_iteration_per_integration": 1e3 * t_numba / n_int,
            "numpy_ms_per_iteration_per_integration": 1e3 * t_numpy / n_int,
            "speedup_over_numpy": t_numpy / t_numba,
            "max_abs_difference_numba_vs_numpy": float(diff),
            "sweep_gbytes_per_s": elements * 20 / t_numba / 1e9,
            "solve_iterations_mean": float(res.iterations.mean()),
            "solve_ms_per_integration_tol_1e-5": 1e3 * t_solve / n_int}


def peel_rates(n_ant=256, n_int=16, n_src=8, passes=5, rng=None, modes=None):
    """Peeling rates; ``modes`` (n_src,) per source (default: every source peeled)."""
    rng = rng or np.random.default_rng(2)
    V, M, W, g, name = _problem(n_ant, n_int, n_src, rng)
    per_source = np.full(n_src, PEEL) if modes is None else np.asarray(modes)
    modes = np.repeat(per_source[:, None], n_int, axis=1)
    kw = dict(passes=passes, tol=1e-4, max_iter=30)
    peel_dense(V[:2], M[:, :2], W[:2], modes[:, :2], **kw)  # compile
    out = {}
    t_cold = best_time(lambda: out.update(cold=peel_dense(V, M, W, modes, **kw)), 2)
    cold = out["cold"]
    # warm start: the previous integration's solution (here the cold one, perturbed as by 13 s)
    warm0 = cold.dd_gains * np.exp(0.05j * rng.normal(size=cold.dd_gains.shape))
    t_warm = best_time(lambda: out.update(warm=peel_dense(V, M, W, modes, warm0, **kw)), 3)
    warm = out["warm"]
    # numpy put-back/subtract of one source beside the numba kernel
    R = V.copy()
    ones = np.ones(n_int)
    t_add = best_time(lambda: add_component(R, M[0], cold.dd_gains[0], ones))
    t_add_np = best_time(
        lambda: np.add(R, cold.dd_gains[0][:, :, None] * M[0] * np.conj(cold.dd_gains[0])[:, None, :], out=R)
    )
    resid = float(np.linalg.norm(cold.residual * W) / np.linalg.norm(V * W))
    per_cold, per_warm = t_cold / n_int, t_warm / n_int
    return {"n_ant": n_ant, "layout": name, "sources": n_src, "passes": passes, "integrations_per_call": n_int,
            "modes": [{PEEL: "peel", SUBTRACT: "subtract", MODEL: "model"}[int(m)] for m in per_source],
            "stefcal_tol": 1e-4, "stefcal_max_iter": 30, "timing": "best of 2 (cold) and 3 (warm) runs",
            "ms_per_integration_cold_start": 1e3 * per_cold, "ms_per_integration_warm_start": 1e3 * per_warm,
            "mean_stefcal_iterations_per_source_cold": float(cold.iterations.mean()),
            "mean_stefcal_iterations_per_source_warm": float(warm.iterations.mean()),
            "guard_fired_fraction": float(cold.guard.mean()),
            "residual_over_data_norm": resid,
            "add_component_ms_numba": 1e3 * t_add / n_int, "add_component_ms_numpy": 1e3 * t_add_np / n_int,
            "add_component_speedup_over_numpy": t_add_np / t_add,
            "projected_minutes_28h_day_one_channel_warm": per_warm * N_DAY / 60,
            "projected_minutes_28h_day_8_channels_warm": per_warm * N_DAY * N_CHANNELS_PAPER / 60,
            "projected_minutes_28h_day_one_channel_cold": per_cold * N_DAY / 60}


#: the paper-scale workflow's peel recipe (workflows/paper-scale.yaml): two peeled, two subtracted,
#: seven modelled sources, the screen DD model, xx and yy
STAGE_RECIPE = {"sources": ["Cyg A", "Cas A", "Vir A", "Tau A"], "peel": ["Cyg A", "Cas A"],
                "model_sources": ["3C 123", "3C 48", "3C 147", "3C 196", "3C 286", "3C 295", "3C 380"]}
N_SIDEREAL_DAY = 6628  # 13 s integrations in a sidereal day: the paper-scale workflow's


def peel_stage_rates(n_ant=256, n_int=32, rng=None):
    """The peel stage's computation on one channel's time chunk, without its reads and writes: the
    models of the paper-scale recipe's eleven sources (``source_coherencies``) and the stage's solve
    (:func:`mmflow.workflow.stages.peel.solve.peel_solve`: modes, screen basis, the batches' antenna
    matrices, the solve in its working precision, back to baselines), both polarisations, on data
    made of the same models with Cyg A and Cas A moved by a refractive offset (3' rms) plus noise,
    at LSTs where both are high. On one core, as a worker of mmflow's local cluster runs a task (one
    worker per core, one thread each): the stage's wall time on ``c`` cores compares with
    ``projected_s_sidereal_day_one_core / c``."""
    with one_core():
        return _peel_stage_rates(n_ant, n_int, rng)


@contextmanager
def one_core():
    """Kernels on one thread (``MMFLOW_THREADS=1``, BLAS limited to one thread) for the block's duration."""
    with restored_environ("MMFLOW_THREADS"):
        os.environ["MMFLOW_THREADS"] = "1"
        with single_threaded_blas():
            yield


def _peel_stage_rates(n_ant, n_int, rng):
    rng = rng or np.random.default_rng(4)
    cfg = load_config(overrides=["telescope.preset=paper-2017", f"telescope.max_antennas={n_ant}",
                                 "beam.type=sin_elevation", "beam.alpha=1.5", "observation.freqs_mhz=[73.152]",
                                 "peel.enabled=true"] + [f"peel.{k}={json.dumps(v)}" for k, v in STAGE_RECIPE.items()])
    p, tel, epoch = cfg.peel, build_telescope(cfg), 2457802.0
    pairs = tel.antenna_pairs()
    lst = np.deg2rad(322.0) + 2 * np.pi / N_SIDEREAL_DAY * np.arange(n_int)  # Cyg A and Cas A high
    names = peel_names(p)
    sources = get_sources(names)
    t0 = time.perf_counter()
    coh = source_coherencies(tel, 73.152e6, lst, sources, epoch, pairs, solve_dtype(p),
                             out=np.empty((len(names), n_int, len(pairs)), solve_dtype(p)))
    t_models = time.perf_counter() - t0
    vec = np.stack([source_vector_date(s, epoch) for s in sources[:2]])
    basis = screen_basis(tel.layout.enu, 73.152e6, sky_tangents_enu(tel, lst, vec))  # (2, time, ant, 2)
    h = screen_gains(basis, np.deg2rad(3 / 60) * rng.normal(size=(2, n_int, 2)), np.ones((2, n_int)))
    vis = coh[2:].sum(0).astype(complex) + sum(coh[s] * gain_products(h[s][..., None], pairs)[..., 0] for s in (0, 1))
    vis = np.repeat(vis[..., None], 2, -1) + 20 * (
        rng.normal(size=vis.shape + (2,)) + 1j * rng.normal(size=vis.shape + (2,))
    )
    weights = np.ones(vis.shape)

    def solve(n):
        return peel_solve(tel, 0, lst[:n], pairs, vis[:n], weights[:n], coh[:, :n], p, epoch, 13.0)

    solve(2)  # compile
    t0 = time.perf_counter()
    out = solve(n_int)
    t_solve = time.perf_counter() - t0
    per = (t_models + t_solve) / n_int
    return {"n_ant": n_ant, "integrations": n_int, "pols": 2, **STAGE_RECIPE, "dd_model": p.dd_model,
            "batch": p.batch, "passes": p.passes, "working_precision": np.dtype(solve_dtype(p)).name,
            "ms_per_integration_models": 1e3 * t_models / n_int, "ms_per_integration_solve": 1e3 * t_solve / n_int,
            "ms_per_integration": 1e3 * per, "peeled_fraction": float((out.mode[:2] == PEEL).mean()),
            "not_converged": int(((out.mode == PEEL) & ~out.converged).sum()),
            "projected_s_sidereal_day_one_core": per * N_SIDEREAL_DAY,
            "projected_s_sidereal_day_all_cores": per * N_SIDEREAL_DAY / usable_cores(), "cores": usable_cores()}


def screened_gain_rates(n_ant=256, n_int=100, rng=None):
    """The gain solve of the default recipe (one track of ``n_int`` 13 s integrations, xx and yy,
    four sources) against the catalogue models and with two of them screened
    (:func:`mmflow.calibrate.screened_gains.solve_gains_screened`, two rounds)."""
    rng = rng or np.random.default_rng(3)
    enu, name = _layout(n_ant)
    i, j = np.triu_indices(n_ant, 1)
    pairs = np.stack([i, j], 1)
    d = rng.normal(size=(4, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.7
    d /= np.linalg.norm(d, axis=1)[:, None]
    b = (enu[j] - enu[i]) / (SPEED_OF_LIGHT / FREQ)
    flux = np.array([16000.0, 14000.0, 2500.0, 1800.0])
    coh = np.stack([np.broadcast_to(f * np.exp(2j * np.pi * b @ x), (n_int, len(i))) for f, x in zip(flux, d)])
    vis = np.repeat(coh.sum(0)[..., None], 2, -1) + 50 * rng.normal(size=(n_int, len(i), 2))
    basis = 100 * rng.normal(size=(4, n_int, n_ant, 2))
    screened = np.array([True, True, False, False])
    solve_gains(vis[:2], coh[:, :2].sum(0)[..., None], 1.0, pairs, n_ant)  # compile
    t_plain = best_time(lambda: solve_gains(vis, coh.sum(0)[..., None], 1.0, pairs, n_ant), 2)
    t_screened = best_time(lambda: solve_gains_screened(vis, coh, 1.0, pairs, n_ant, basis, screened, rounds=2), 1)
    return {"n_ant": n_ant, "layout": name, "integrations": n_int, "pols": 2, "sources": 4, "screened": 2,
            "rounds": 2, "s_catalogue_models": t_plain, "s_screened": t_screened,
            "screened_over_catalogue": t_screened / t_plain}


def terrestrial_sky_loss_rates(n_ant=256, rng=None):
    """Seconds of the terrestrial stage's driver step for one channel (:func:`template_sky_loss`: two random
    rank-1 patterns, both polarisations, every cross baseline used) and the loss it finds (templates unrelated
    to the sky: ~``K^2 / (2 n_bl)``)."""
    rng = rng or np.random.default_rng(3)
    enu, name = _layout(n_ant)
    pairs = np.stack(np.triu_indices(n_ant, 1), 1)  # the cross baselines, as screened_gain_rates
    used = np.ones(len(pairs), bool)
    patterns = rng.normal(size=(2, n_ant, 2)) + 1j * rng.normal(size=(2, n_ant, 2))
    beam = SinElevationBeam(1.5)

    def step():
        return template_sky_loss(patterns, pairs, enu, FREQ, np.ones((len(pairs), 2)), used, np.deg2rad(37.24),
                                 beam.power_enu)
    t = best_time(step, reps=2)
    return {"layout": name, "antennas": n_ant, "baselines_used": int(min(used.sum(), LOSS_BASELINES)),
            "track_points": list(TRACK_POINTS), "seconds_per_channel": t, "sky_loss": step(),
            "random_template_expectation": len(patterns) ** 2 / (2 * min(used.sum(), LOSS_BASELINES))}


def run(what="calibrate", quick=False):
    """All figures as a dict (JSON-able)."""
    n_ant = 64 if quick else 256
    res = {"machine": machine(), "threads": n_threads(), "sgemm_gflops_peak": gemm_gflops(np.float32),
           "memory_copy_gbytes_per_s_peak": memory_bandwidth_gbs()}
    res["stefcal"] = stefcal_rates(n_ant)
    res["peel"] = peel_rates(n_ant, n_int=4 if quick else 16)
    # the calibration demo's recipe: two peeled, two subtracted, seven fainter sources modelled
    res["peel_demo_recipe"] = peel_rates(n_ant, n_int=4 if quick else 16, n_src=11,
                                         modes=[PEEL] * 2 + [SUBTRACT] * 2 + [MODEL] * 7)
    res["gains_screened"] = screened_gain_rates(n_ant, n_int=20 if quick else 100)
    # what the peel stage computes per time chunk (paper-scale recipe, both hands, screen model)
    res["peel_stage"] = peel_stage_rates(n_ant, n_int=4 if quick else 32)
    res["terrestrial_sky_loss"] = terrestrial_sky_loss_rates(n_ant)
    s = res["stefcal"]
    res["stefcal"]["projected_minutes_28h_day_one_channel_per_iteration"] = (
        s["ms_per_iteration_per_integration"] * N_DAY / 6e4)
    res["targets"] = {"stefcal_ms_per_iteration_per_integration": 5.0, "peel_ms_per_integration": 50.0}
    return res


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))  # same as `mmflow bench calibrate`
