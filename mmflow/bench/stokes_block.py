"""``mmflow bench stokes-block``: the stokes stage's block tasks at the paper's scale, measured on a fraction of
the baselines, beside the stage's cost model.

The stage's own code (:func:`mmflow.workflow.stages.stokes.stage.block_normal` and ``block_solve``) runs each
block of m of the paper's channel (``workflows/paper-scale.yaml`` with ``imaging.stokes=[I, Q, U, V]`` and
the short-dipole beam; ``--set`` for more) on ``1/fraction`` of its baselines (a fixed random draw: every
length, as the stage's chunks sorted by per-baseline lmax see them), with random m-modes in their place (the
work does not depend on their values), BLAS on one thread as in every task. Per block it reports the measured
seconds by part (``grid``: the chunk grids made; ``ring``: the ring products and FFTs; ``gemm``: the m pool's
Legendre GEMMs, ``herk`` and right-hand sides; ``factor``: the solve, each m factorised once; ``other``: the
rest of the accumulation: its Grams' allocation and completion), the model's figures for the same baselines
(:func:`mmflow.workflow.stages.stokes.cost.block_parts`, at the SGEMM peak measured in the same run) and
their ratios; then the whole task projected (``ring`` and ``gemm`` scale with the baselines, ``x fraction``;
the grids by the model's ratio of the full task's to the subset's; ``factor`` and ``other`` as measured)
beside the model's whole task. The stage's wall time on the workflow's workers is the plan's
(``plan_stage_s``).
"""
from __future__ import annotations

import time

import numpy as np

from mmflow.machine import gemm_gflops, machine
from mmflow.mmode.polarised import CORRELATIONS
from mmflow.threads import blas_on_one_thread, n_threads

WORKFLOW = "workflows/paper-scale.yaml"
OVERRIDES = ["imaging.stokes=[I, Q, U, V]", "beam={type: short_dipole, horizon_taper: 3}", "sky.diffuse=false"]


def _timed_grids(out):
    """Wrap a stage grid function so that the seconds and points of the grids it makes add to ``out``."""
    def wrap(grid_of):
        made = {}

        def timed(top, index):
            t0 = time.perf_counter()
            grid = grid_of(top, index)
            if id(grid) not in made:  # a grid made now, not the kept one
                made.clear()
                made[id(grid)] = grid
                out["grid_s"] += time.perf_counter() - t0
                out["grid_points"] += len(grid.theta) * grid.n_phi
            return grid
        return timed
    return wrap


def measure_block(cfg, tel, freq, pairs, m_range, n_split, seed=0):
    """Seconds by part of one block task on baselines ``pairs`` (module docstring)."""
    from mmflow.workflow.stages.stokes.stage import block_normal, block_solve  # deferred: workflow modules

    m0, m1 = m_range
    rng = np.random.default_rng(seed)
    shape = (n_split, m1 - m0, 2, len(CORRELATIONS), len(pairs))
    mm = rng.standard_normal(shape) + 1j * rng.standard_normal(shape)
    out = {"grid_s": 0.0, "grid_points": 0}
    tim = {}
    with blas_on_one_thread():
        t0 = time.perf_counter()
        normal = block_normal(cfg, tel, freq, pairs, mm, np.ones((len(CORRELATIONS), len(pairs))), m_range,
                              timings=tim, grids=_timed_grids(out))
        acc = time.perf_counter() - t0
        t0 = time.perf_counter()
        block_solve(cfg, normal)
        out["factor_s"] = time.perf_counter() - t0
    out["ring_s"], out["gemm_s"] = tim.get("fourier_s", 0.0), tim.get("mpool_s", 0.0)
    out["other_s"] = acc - out["ring_s"] - out["gemm_s"] - out["grid_s"]
    return out


def run(what, quick=False, fraction=None, blocks=None, overrides=()):
    from mmflow.workflow.config.schema import load_config  # deferred: workflow modules (~3 s)
    from mmflow.workflow.engine.geometry import stokes_lmax_of
    from mmflow.workflow.plan.planner import geometry, plan
    from mmflow.workflow.stages.stokes import cost
    from mmflow.workflow.stages.stokes.blocks import blocks_of, sizes_of

    extra = ["telescope.max_antennas=64", "mmode.lmax=200"] if quick else []
    cfg = load_config(WORKFLOW, OVERRIDES + extra + list(overrides))
    fraction = fraction or (8 if quick else 128)
    g = geometry(cfg)
    tel, freq = g.tel, g.freqs_hz[-1]
    all_blocks = blocks_of(cfg, g.n_split, g.n_bl)
    chosen = range(len(all_blocks)) if blocks is None else blocks
    pairs = tel.antenna_pairs()
    sub = np.sort(np.random.default_rng(1).choice(len(pairs), max(1, len(pairs) // fraction), replace=False))
    order, lb, b_len, n_theta = cost._baselines(g, cfg)
    subset = (np.argsort(lb[sub], kind="stable"), lb[sub], b_len[sub], n_theta)
    size, lmax_p, threads = sizes_of(cfg), stokes_lmax_of(cfg), n_threads()
    peak = gemm_gflops(np.float32)
    res = {"machine": machine(), "workflow": WORKFLOW, "overrides": OVERRIDES + extra + list(overrides),
           "baselines": len(pairs), "measured_baselines": len(sub), "fraction": len(pairs) / len(sub),
           "threads": threads, "sgemm_gflops": peak, "blocks": []}
    for bi in chosen:
        m0, m1 = all_blocks[bi]
        meas = measure_block(cfg, tel, freq, pairs[sub], (m0, m1), g.n_split)
        res["blocks"].append({"m": [m0, m1], "measured": meas})
    res["sgemm_gflops_after"] = gemm_gflops(np.float32)
    best = max(peak, res["sgemm_gflops_after"])
    core = cost.core_gflops(best)
    scale = res["fraction"]
    for blk in res["blocks"]:
        (m0, m1), meas = blk["m"], blk["measured"]
        part = cost.block_parts(g, cfg, subset, m0, m1, size, lmax_p, core)
        full = cost.block_parts(g, cfg, (order, lb, b_len, n_theta), m0, m1, size, lmax_p, core)
        blk["model_subset_thread_s"] = part
        # ring and gemm run on the task's threads (the model's thread-seconds over them), grids and factors on one
        blk["measured_over_model"] = {k: meas[f"{k}_s"] * (threads if k in ("ring", "gemm") else 1) / v
                                      for k, v in part.items() if v > 0}
        grid_full = meas["grid_s"] * full["grid"] / part["grid"] if part["grid"] else 0.0
        blk["projected_full_task_s"] = ((meas["ring_s"] + meas["gemm_s"]) * scale + grid_full + meas["factor_s"]
                                        + meas["other_s"])
        blk["model_full_task_s"] = cost.block_seconds(full, threads)
    res["projected_block_tasks_s"] = sum(b["projected_full_task_s"] for b in res["blocks"])
    res["model_block_tasks_s"] = sum(b["model_full_task_s"] for b in res["blocks"])
    res["plan_stage_s"] = next(s["seconds"] for s in plan(cfg, peak_gflops=best)["stages"] if s["stage"] == "stokes")
    return res
