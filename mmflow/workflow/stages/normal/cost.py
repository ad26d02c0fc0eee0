"""The normal stage's cost: a task per channel and m block summing the transfer stage's partial Grams
of that block over the ``G`` baseline groups (the units: the block's elements times the groups).

Its working set is the block's packed upper triangles (``E`` elements, as the stores hold them) in the
arrays :func:`mmflow.workflow.engine.reduce.ordered_tree_sum` holds at its peak, complex128 each::

    W = 16 E (P + 3),     P = max_{k < G} popcount(k)

``P`` pending partial sums (after ``k`` parts the stack holds one sum per set bit of ``k``), the part
just read (cast to complex128), its copy on the stack, and a pair's sum while both halves live.
Measured: 4.0 W/16E at G = 2 (lmax 1000: 0.514 GB for E = 8.0e6), ~6.5 at G = 8 (the squares' era).
"""
from __future__ import annotations

from mmflow.io import run_stores as rs
from mmflow.workflow.plan.work import COMPLEX128_BYTES, Cost, Work, block_sum, halvings, n_m_blocks, packed_block_sum

#: arrays a pairwise sum holds besides its pending partial sums: the part read, its copy, a pair's sum
TREE_SUM_EXTRA_ARRAYS = 3


def tree_sum_arrays(n_parts):
    """Complex128 arrays of one block an ordered tree sum of ``n_parts`` holds at its peak, ``P + 3``."""
    return max(bin(k).count("1") for k in range(max(int(n_parts), 1))) + TREE_SUM_EXTRA_ARRAYS


def work(g, cfg):
    blk2 = block_sum(g.lmax, g.mmax, g.m_block, 2)
    spec = rs.normal_store(g.n_freq, g.lmax, g.mmax, g.m_block, g.n_split, g.gram_dtype)
    packed = packed_block_sum(g.lmax, g.mmax, g.m_block)
    return Work(g.n_freq * n_m_blocks(g), packed * COMPLEX128_BYTES * tree_sum_arrays(g.n_groups),
                blk2 * g.n_groups, [spec])


COST = Cost(work, shrink="a smaller transfer.m_block", split=halvings("transfer.m_block"))
