"""The ``solve`` stage (per frequency and m block).

It calls :func:`mmflow.imaging.solvers.solve_m` (the engine's own per-m loop) on the
reduced normal equations and writes ``alm.zarr``: ``alm`` per data split in Jy/sr in the frame
of date, ``lcurve`` (first split) and ``fraction_above``.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import healpy
import numpy as np

from mmflow.conventions import m_blocks, m_slice
from mmflow.imaging.lcurve import default_eps_grid
from mmflow.imaging.solvers import solve_m
from mmflow.io.run_stores import VIS_METADATA, STORES, alm_store
from mmflow.mmode.normal import hermitian_block
from mmflow.sky.diffuse import map_to_alm
from mmflow.sky.frames import rotate_alm, rotation_matrix
from mmflow.threads import n_threads, single_threaded_blas
from mmflow.workflow.engine.geometry import mmax_of
from mmflow.workflow.engine.kernel_args import m_filters
from mmflow.workflow.stages.solve.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey

N_EPS = 200
SOLVE_CONFIG = ("mmode.lmax", "mmode.mmax", "transfer.m_block", "imaging", "products.frame")


def _solve_prepare(ctx):
    cfg = ctx.cfg
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    ng = ctx.open(STORES.normal)
    n_split, nf = ng[STORES.normal.rhs].shape[:2]
    ctx.create(alm_store(nf, lmax, mmax, cfg.transfer.m_block, n_split, default_eps_grid(N_EPS)))
    return [TaskKey(freq=fi, m_block=m0) for fi in range(nf) for m0, _ in m_blocks(mmax, cfg.transfer.m_block)]


def _prior_alm(ctx, lmax):
    """The prior map (``imaging.prior_map``, in ``products.frame``) as alm in the frame of date."""
    cfg = ctx.cfg
    hmap = healpy.read_map(cfg.imaging.prior_map)
    epoch = ctx.vis_attrs()["epoch_jd"]
    return rotate_alm(map_to_alm(hmap, lmax), rotation_matrix(cfg.products.frame, "date", epoch), lmax)


def _solve_task(ctx, key):
    cfg = ctx.cfg
    im = cfg.imaging
    fi, m0 = key.freq, key.m_block
    m1 = dict(m_blocks(mmax_of(cfg), cfg.transfer.m_block))[m0]
    lmax = cfg.mmode.lmax
    rhs_all = ctx.read(STORES.normal.rhs, (slice(None), slice(fi, fi + 1), slice(m0, m1)))[:, 0]
    vhv_all = ctx.read(STORES.normal.vhv, (slice(None), slice(fi, fi + 1), slice(m0, m1)))[:, 0]
    grams = ctx.read(STORES.normal.gram(fi, m0))
    prior = _prior_alm(ctx, lmax) if im.method == "prior" else None
    eps_grid = default_eps_grid(N_EPS) if im.lcurve else None
    n_split = rhs_all.shape[0]
    alm = np.zeros((n_split, 1, m1 - m0, lmax + 1), np.complex128)
    lc = np.zeros((1, m1 - m0, N_EPS, 2))
    frac = np.zeros((1, m1 - m0))

    def one(m):
        gram = hermitian_block(grams[m - m0], lmax - m0 + 1, lmax - m + 1)
        return solve_m(gram, rhs_all[:, m - m0, m:], m, lmax, im.method, im.eps, m_filters(im),
                       None if prior is None else prior[m_slice(lmax, m)], vhv_all[0, m - m0], eps_grid)

    # the m blocks of the task on the task's thread budget, one BLAS thread each (same bits on any cluster)
    with single_threaded_blas(), ThreadPoolExecutor(max_workers=n_threads()) as pool:
        sols = list(pool.map(one, range(m0, m1)))
    for m, sol in zip(range(m0, m1), sols):
        alm[:, 0, m - m0, m:] = sol.alm
        frac[0, m - m0] = sol.fraction_above
        if sol.lcurve is not None:
            lc[0, m - m0] = sol.lcurve
    out = ctx.open(STORES.alm, mode="r+")
    ctx.write(out, STORES.alm.alm, (slice(None), slice(fi, fi + 1), slice(m0, m1)), alm)
    ctx.write(out, STORES.alm.lcurve, (slice(fi, fi + 1), slice(m0, m1)), lc)
    ctx.write(out, STORES.alm.fraction_above, (slice(fi, fi + 1), slice(m0, m1)), frac)
    return {"m": [m0, m1]}


def _prior_files(cfg):
    return [cfg.imaging.prior_map] if cfg.imaging.method == "prior" and cfg.imaging.prior_map else []


STAGE = Stage("solve", SOLVE_CONFIG, (STORES.vis, STORES.normal), (STORES.alm,), _solve_prepare, _solve_task,
               files=_prior_files, description="Tikhonov (or alternative) solve + L-curve per m block", cost=COST,
               reads={STORES.vis: VIS_METADATA})
