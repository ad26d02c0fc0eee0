"""The solve stage's cost: a task per channel and m block factoring its Gram block (the units:
``sum_m (lmax - m + 1)^3``, Cholesky's flops). Its working set: the block as read (packed upper triangles in
the Grams' precision) and the complex128 work of its m beyond that, ``sum_m (lmax - m + 1)^2 (16 - itemsize)``
(with the block read as squares, the two made ``sum_m (lmax - m + 1)^2 16``, which the constants were fitted
on)."""
from __future__ import annotations

import numpy as np

from mmflow.io import run_stores as rs
from mmflow.workflow.plan.work import COMPLEX128_BYTES, Cost, Work, block_sum, halvings, n_m_blocks, packed_block_sum

#: eps values of an L-curve (``alm.zarr`` eps_grid)
LCURVE_POINTS = 200


def work(g, cfg):
    blk2 = block_sum(g.lmax, g.mmax, g.m_block, 2)
    spec = rs.alm_store(g.n_freq, g.lmax, g.mmax, g.m_block, g.n_split, np.zeros(LCURVE_POINTS))
    read = packed_block_sum(g.lmax, g.mmax, g.m_block) * g.gram_itemsize
    return Work(g.n_freq * n_m_blocks(g), read + blk2 * (COMPLEX128_BYTES - g.gram_itemsize),
                block_sum(g.lmax, g.mmax, g.m_block, 3), [spec])


COST = Cost(work, shrink="a smaller transfer.m_block", split=halvings("transfer.m_block"))
