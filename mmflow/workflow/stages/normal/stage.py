"""The ``normal`` stage (reduce): one task per (frequency, m block) sums the transfer stage's
partial normal equations over the fixed baseline groups with
:func:`mmflow.workflow.engine.reduce.ordered_tree_sum`: bit-identical on any cluster.
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import m_blocks
from mmflow.io.run_stores import STORES, normal_store
from mmflow.workflow.engine.reduce import ordered_tree_sum
from mmflow.workflow.engine.geometry import mmax_of
from mmflow.workflow.stages.normal.cost import COST
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey


def _normal_prepare(ctx):
    cfg = ctx.cfg
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    pg = ctx.open(STORES.partials)
    nf = len(list(pg.group_keys()))
    n_split = pg[STORES.partials.rhs(0)].shape[1]
    ctx.create(normal_store(nf, lmax, mmax, cfg.transfer.m_block, n_split, pg[STORES.partials.gram(0, 0)].dtype.str))
    return [TaskKey(freq=fi, m_block=m0) for fi in range(nf) for m0, _ in m_blocks(mmax, cfg.transfer.m_block)]


def _normal_task(ctx, key):
    fi, m0 = key.freq, key.m_block
    cfg = ctx.cfg
    m1 = dict(m_blocks(mmax_of(cfg), cfg.transfer.m_block))[m0]
    pg = ctx.open(STORES.partials)
    ng = pg[STORES.partials.rhs(fi)].shape[0]
    g = ctx.open(STORES.normal, mode="r+")
    gram = ordered_tree_sum(ctx.read(STORES.partials.gram(fi, m0), (slice(k, k + 1),))[0].astype(np.complex128)
                            for k in range(ng))
    name = STORES.normal.gram(fi, m0)
    ctx.write(g, name, (), gram.astype(g[name].dtype))  # summed in complex128, rounded once
    rhs = ordered_tree_sum(ctx.read(STORES.partials.rhs(fi), (slice(k, k + 1),))[0, :, m0:m1]
                           .astype(np.complex128) for k in range(ng))
    vhv = ordered_tree_sum(ctx.read(STORES.partials.vhv(fi), (slice(k, k + 1),))[0, :, m0:m1]
                           for k in range(ng))
    ctx.write(g, STORES.normal.rhs, (slice(None), slice(fi, fi + 1), slice(m0, m1)), rhs[:, None])
    ctx.write(g, STORES.normal.vhv, (slice(None), slice(fi, fi + 1), slice(m0, m1)), vhv[:, None])
    return {"m": [m0, m1]}


STAGE = Stage(
    "normal",
    ("mmode.lmax", "mmode.mmax", "transfer.m_block"),
    (STORES.partials,),
    (STORES.normal,),
    _normal_prepare,
    _normal_task,
    kind="reduce",
    description="sum partial normal equations over baseline groups (fixed-order tree), per m block",
    cost=COST,
    by_channel_after="transfer",  # each channel's partials summed, and released, before the next is made
)
