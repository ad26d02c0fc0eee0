"""The normal stage's cost: a task per channel and m block summing the transfer stage's partial Grams
of that block (the block's packed upper triangles in complex128; the units: the block's elements times the
groups)."""
from __future__ import annotations

from mmflow.io import run_stores as rs
from mmflow.workflow.plan.work import COMPLEX128_BYTES, Cost, Work, block_sum, halvings, n_m_blocks, packed_block_sum


def work(g, cfg):
    blk2 = block_sum(g.lmax, g.mmax, g.m_block, 2)
    spec = rs.normal_store(g.n_freq, g.lmax, g.mmax, g.m_block, g.n_split, g.gram_dtype)
    packed = packed_block_sum(g.lmax, g.mmax, g.m_block)
    return Work(g.n_freq * n_m_blocks(g), packed * COMPLEX128_BYTES, blk2 * g.n_groups, [spec])


COST = Cost(work, shrink="a smaller transfer.m_block", split=halvings("transfer.m_block"))
