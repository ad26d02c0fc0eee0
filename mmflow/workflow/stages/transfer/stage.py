"""The ``transfer`` stage: streaming normal equations per fixed baseline group.

``transfer`` (map): one task per (frequency, baseline group). Groups are a fixed number
(``transfer.groups``) of contiguous runs of baseline chunks sorted by per-baseline lmax
(:func:`mmflow.mmode.engine.plan_groups`): the decomposition depends on the settings,
never on the cluster. A task streams over its chunks with
:func:`mmflow.mmode.engine.accumulate_chunks` (the engine's own loop) and writes its partial
``G_m``, ``r_m`` and ``v^H N^-1 v`` to ``partials.zarr`` at its group index.
The ``normal`` stage (:mod:`.normal`) reduces the partials.
"""
from __future__ import annotations

import time

import numpy as np

from mmflow.conventions import m_blocks, complex_dtype
from mmflow.io.run_stores import VIS_METADATA, STORES, partials_store, transfer_store
from mmflow.mmode.engine import GridCache, accumulate_chunks, plan_chunks, plan_groups
from mmflow.mmode.noise import relative_weights
from mmflow.mmode.normal import NormalAccumulator, pack_upper
from mmflow.workflow.engine.geometry import mmax_of
from mmflow.workflow.stages.transfer.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey

TRANSFER_CONFIG = ("mmode.lmax", "mmode.mmax", "transfer", "beam")


def _plan(ctx, fi):
    cfg = ctx.cfg
    tel = ctx.telescope()
    chunks, lmax_b = plan_chunks(tel, tel.freqs_hz[fi], cfg.mmode.lmax, cfg.transfer.baseline_chunk,
                                 cfg.transfer.per_baseline_lmax)
    return tel, chunks, lmax_b, plan_groups(chunks, cfg.transfer.groups)


def _acc_dtype(cfg):
    return complex_dtype(cfg.transfer.dtype).name


def _transfer_prepare(ctx):
    cfg = ctx.cfg
    tel = ctx.telescope()
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    tel.check_lmax(lmax)
    mg = ctx.open(STORES.mmodes)
    n_split, nf = mg[STORES.mmodes.mmodes].shape[:2]
    plans = [_plan(ctx, fi) for fi in range(nf)]
    n_groups = max(len(p[3]) for p in plans)
    ctx.create(partials_store(nf, n_groups, lmax, mmax, cfg.transfer.m_block, n_split, _acc_dtype(cfg)))
    if cfg.transfer.mode == "store":
        orders = [np.concatenate([c.index for c in p[1]]).astype("int64") for p in plans]
        ctx.create(transfer_store(nf, len(tel.antenna_pairs()), lmax, mmax, cfg.transfer.baseline_chunk,
                                  _acc_dtype(cfg), orders))
    return [TaskKey(freq=fi, group=k) for fi, p in enumerate(plans) for k in range(n_groups)]


def _transfer_task(ctx, key):
    cfg = ctx.cfg
    fi, gk = key.freq, key.group
    tel, chunks, lmax_b, groups = _plan(ctx, fi)
    f = tel.freqs_hz[fi]
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    group = groups[gk] if gk < len(groups) else []
    t0 = time.perf_counter()
    # only the group's baselines are kept (all of them are 1 GB at the paper's channel), in the
    # group's chunk order: chunk k's m-modes are columns starts[k]:starts[k + 1]
    cols = np.concatenate([c.index for c in group]) if group else np.zeros(0, int)
    starts = dict(zip((id(c) for c in group), np.cumsum([0] + [len(c.index) for c in group])))
    mm_group = ctx.read(STORES.mmodes.mmodes, (slice(None), slice(fi, fi + 1)))[:, 0][..., cols]
    inv_var = ctx.read(STORES.mmodes.inv_var, (slice(fi, fi + 1),))[0]
    tim = {"read_s": time.perf_counter() - t0}
    inv_var = relative_weights(inv_var) if cfg.transfer.noise_weighting else np.ones_like(inv_var)
    dtype = np.float32 if cfg.transfer.dtype == "float32" else np.float64
    # accumulators follow the transfer precision: complex64 halves the ~lmax^3/3 Gram memory
    acc = NormalAccumulator(lmax, mmax, np.dtype(_acc_dtype(cfg)), n_split=mm_group.shape[0])
    on_block = None
    if cfg.transfer.mode == "store":
        on_block = _block_writer(ctx, fi, chunks, cfg.transfer.baseline_chunk)
    t0 = time.perf_counter()
    accumulate_chunks(acc, tel, f, group, lmax_b, lambda c: mm_group[..., starts[id(c)]:starts[id(c)] + len(c.index)],
                      inv_var, dtype, GridCache(tel, f), on_block, timings=tim)
    tim["accumulate_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pg = ctx.open(STORES.partials, mode="r+")
    for m0, m1 in m_blocks(mmax, cfg.transfer.m_block):
        n0 = lmax - m0 + 1
        blk = np.zeros((1, m1 - m0, n0, n0), acc.dtype)
        for m in range(m0, m1):
            blk[0, m - m0, :lmax - m + 1, :lmax - m + 1] = acc.gram[m]
        ctx.write(pg, STORES.partials.gram(fi, m0), (slice(gk, gk + 1),), pack_upper(blk))
    rhs = np.zeros((1, acc.n_split, mmax + 1, lmax + 1), acc.dtype)
    for m in range(mmax + 1):
        rhs[0, :, m, m:] = acc.rhs[m]
    ctx.write(pg, STORES.partials.rhs(fi), (slice(gk, gk + 1),), rhs)
    ctx.write(pg, STORES.partials.vhv(fi), (slice(gk, gk + 1),), acc.vhv[None])
    tim["write_s"] = time.perf_counter() - t0
    # per-phase seconds (pool phases in thread-seconds) for `mmflow bench channel`
    return {"baselines": int(sum(len(c.index) for c in group)), "timings": {k: round(v, 3) for k, v in tim.items()}}


def _block_writer(ctx, fi, chunks, bc):
    """Write each transfer block of a chunk at its rows of ``transfer.zarr`` (chunks in lmax order)."""
    store = ctx.open(STORES.transfer, mode="r+")
    # chunks are contiguous in the lmax order and their sizes multiples of bc: rows stay chunk-aligned
    starts = np.concatenate([[0], np.cumsum([len(c.index) for c in chunks])])
    position = {id(c): int(starts[k]) for k, c in enumerate(chunks)}

    def write(chunk, m, blk):
        n = len(chunk.index)
        b2 = np.zeros((2, n, blk.shape[1]), blk.dtype)
        b2[0] = blk[:n]
        if m > 0:
            b2[1] = blk[n:]
        row0 = position[id(chunk)]
        ctx.write(store, STORES.transfer.B(fi, m), (slice(None), slice(row0, row0 + n)), b2)
    return write


STAGE = Stage("transfer", TRANSFER_CONFIG, (STORES.vis, STORES.mmodes), (STORES.partials, STORES.transfer),
               _transfer_prepare, _transfer_task,
               description="transfer blocks + herk into partial normal equations per fixed baseline group", cost=COST,
               reads={STORES.vis: VIS_METADATA, STORES.mmodes: ("mmodes", "inv_var")})
