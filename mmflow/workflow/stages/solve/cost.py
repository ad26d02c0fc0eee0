"""The solve stage's cost: a task per channel and m block factoring its Gram block (the units:
``sum_m (lmax - m + 1)^3``, Cholesky's flops).

Its working set is the larger of two phases. Reading the block (packed upper triangles in the Grams'
precision, ``P`` bytes) holds :data:`~mmflow.workflow.plan.work.ZARR_READ_COPIES` ``P``. Solving holds the
block as read, its solutions and L-curves, and on each of the task's threads (one m at a time,
:func:`mmflow.imaging.solvers.solve_m`) :data:`SOLVER_SQUARES` complex128 ``n x n`` arrays of its largest m,
``n = lmax - m0 + 1``::

    W = max(ZARR_READ_COPIES P, P + outputs + min(threads, m_block) SOLVER_SQUARES 16 n^2)
"""
from __future__ import annotations

import numpy as np

from mmflow.io import run_stores as rs
from mmflow.workflow.plan.work import (COMPLEX128_BYTES, ZARR_READ_COPIES, Cost, Work, block_sum, halvings, n_m_blocks,
                                       packed_block_sum)

#: eps values of an L-curve (``alm.zarr`` eps_grid)
LCURVE_POINTS = 200
#: ``n x n`` complex128 arrays a thread holds at once while it solves one m: the full Gram
#: (:func:`mmflow.mmode.normal.hermitian_block`) and, at its peak, the eigen-decomposition's eigenvectors and two
#: arrays' worth of LAPACK work (:func:`mmflow.imaging.lcurve.hermitian_eig`); then the eigenvectors and the
#: Cholesky factor (:func:`mmflow.imaging.solvers.tikhonov`), or at a filtered m the kept coefficients' copy
#: and its factor. Traced at lmax 200: 4.0 of them at an unfiltered m, 3.0 at a filtered one (``tracemalloc``).
SOLVER_SQUARES = 4


def work(g, cfg):
    n = g.lmax + 1  # the first block's first m, m0 = 0: the largest
    spec = rs.alm_store(g.n_freq, g.lmax, g.mmax, g.m_block, g.n_split, np.zeros(LCURVE_POINTS))
    read = packed_block_sum(g.lmax, g.mmax, g.m_block) * g.gram_itemsize
    out = min(g.m_block, g.mmax + 1) * ((g.n_split + 1) * n * COMPLEX128_BYTES + LCURVE_POINTS * 2 * 8)
    solver = min(g.task_threads, g.m_block) * SOLVER_SQUARES * n * n * COMPLEX128_BYTES
    return Work(g.n_freq * n_m_blocks(g), max(ZARR_READ_COPIES * read, read + out + solver),
                block_sum(g.lmax, g.mmax, g.m_block, 3), [spec])


COST = Cost(work, shrink="a smaller transfer.m_block", split=halvings("transfer.m_block"))
