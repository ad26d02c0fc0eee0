"""The clean stage's cost: per channel and m block a PSF task and one task a major cycle; residuals are
written per cycle, so the disk holds the cycles run, not ``clean.max_cycles`` (the plan assumes
``EXPECTED_CLEAN_CYCLES``).

A task holds its block's Cholesky factors, complex128 ``n x n`` each (``B2 = sum_m n^2`` elements, the kept
corner of each m), beside the factors packed (``P`` bytes, ``clean.zarr``'s ``chol_b``: the PSF task writes
them, a cycle task reads them); a cycle task's read holds
:data:`~mmflow.workflow.plan.work.ZARR_READ_COPIES` ``P`` first::

    W = max(ZARR_READ_COPIES P, P + 16 B2)

(the PSF task's Gram read, in the Grams' precision, is at most half of ``P``). Traced on the reduced paper
run's first block (lmax 200, one thread): PSF task 16.1 MB, cycle task 16.5, against 15.6 modelled.
"""
from __future__ import annotations

from mmflow.io import run_stores as rs
from mmflow.workflow.plan.work import (COMPLEX128_BYTES, FEWER_CHANNELS, Cost, PSF_DECLINATIONS, Work, block_sum,
                                       expected_clean_cycles, halvings, n_m_blocks, packed_block_sum, ZARR_READ_COPIES)


def work(g, cfg):
    c = cfg.clean
    cycles = expected_clean_cycles(cfg)
    spec = rs.clean_store(g.n_freq, g.lmax, g.mmax, g.m_block, PSF_DECLINATIONS, cycles, c.peaks_per_cycle, g.npix,
                          c.keep_factors)
    tasks = g.n_freq * n_m_blocks(g) * (1 + cycles)
    factors = block_sum(g.lmax, g.mmax, g.m_block, 2) * COMPLEX128_BYTES
    packed = packed_block_sum(g.lmax, g.mmax, g.m_block) * COMPLEX128_BYTES
    return Work(tasks, max(ZARR_READ_COPIES * packed, packed + factors), block_sum(g.lmax, g.mmax, g.m_block, 3),
                [spec])


def disk_shrink(cfg):
    if cfg.clean.keep_factors:
        return "clean.keep_factors=false (no Cholesky factors on disk)"
    return FEWER_CHANNELS


def notes(g, cfg, peak_gflops):
    return [f"assumes {expected_clean_cycles(cfg)} major cycles: their number depends on the sky"]


COST = Cost(work, shrink="a smaller transfer.m_block", disk_shrink=disk_shrink, notes=notes,
            split=halvings("transfer.m_block"))
