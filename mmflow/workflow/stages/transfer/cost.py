"""The transfer stage's cost: a task per channel and baseline group; its peak is the larger of its read
(the channel's m-modes, before its Gram exists) and its accumulation: its partial Gram (one channel's
``sum_m (lmax - m + 1)^2`` elements) and its workspace (the group's m-modes, grid tables, and the widest
chunk's grid, ring-Fourier buffers and data: :func:`mmflow.workflow.plan.work.transfer_plan`); the units:
the group's Gram updates and its Fourier stage's fringe samples (at a low lmax with long baselines, most
of its time)."""
from __future__ import annotations

import numpy as np

from mmflow.io import run_stores as rs
from mmflow.workflow.plan.work import Cost, Work, gram_bytes, halvings


def work(g, cfg):
    gram = max(gram_bytes(g.lmax, g.mmax, g.gram_itemsize) + g.transfer_workspace, g.transfer_read)
    per_group = max(max(u) for u in g.transfer_units)
    out = [rs.partials_store(g.n_freq, g.n_groups, g.lmax, g.mmax, g.m_block, g.n_split, g.gram_dtype)]
    if cfg.transfer.mode == "store":
        out.append(rs.transfer_store(g.n_freq, g.n_bl, g.lmax, g.mmax, cfg.transfer.baseline_chunk,
                                     g.gram_dtype, [np.zeros(g.n_bl, int)] * g.n_freq))
    return Work(sum(len(u) for u in g.transfer_units), gram, per_group, out)


def disk_shrink(cfg):
    t = cfg.transfer
    return ("transfer.mode=normal (no transfer blocks on disk)" if t.mode != "normal" else
            f"fewer transfer.groups (now {t.groups}: each keeps a partial Gram per channel on disk)")


def shrink(cfg):
    if cfg.transfer.dtype != "float32":
        return "transfer.dtype=float32 (half the Gram)"
    return "a lower mmode.lmax (the Gram and the grid tables grow as lmax^3)"


#: fewer baselines per chunk: smaller ring-Fourier buffers (the Gram and the grid tables stay)
COST = Cost(work, shrink=shrink, disk_shrink=disk_shrink, split=halvings("transfer.baseline_chunk"))
