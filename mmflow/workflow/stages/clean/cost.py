"""The clean stage's cost: per channel and m block a PSF task and one task a major cycle, each holding
a Gram block and its factor (complex128); residuals are written per cycle, so the disk holds the cycles
run, not ``clean.max_cycles`` (the plan assumes ``EXPECTED_CLEAN_CYCLES``)."""
from __future__ import annotations

from mmflow.io import run_stores as rs
from mmflow.workflow.plan.work import (COMPLEX128_BYTES, FEWER_CHANNELS, Cost, PSF_DECLINATIONS, Work, block_sum,
                                       expected_clean_cycles, halvings, n_m_blocks)


def work(g, cfg):
    c = cfg.clean
    cycles = expected_clean_cycles(cfg)
    spec = rs.clean_store(g.n_freq, g.lmax, g.mmax, g.m_block, PSF_DECLINATIONS, cycles, c.peaks_per_cycle, g.npix,
                          c.keep_factors)
    tasks = g.n_freq * n_m_blocks(g) * (1 + cycles)
    blk2 = block_sum(g.lmax, g.mmax, g.m_block, 2)
    return Work(tasks, blk2 * COMPLEX128_BYTES * 2, block_sum(g.lmax, g.mmax, g.m_block, 3), [spec])


def disk_shrink(cfg):
    if cfg.clean.keep_factors:
        return "clean.keep_factors=false (no Cholesky factors on disk)"
    return FEWER_CHANNELS


def notes(g, cfg, peak_gflops):
    return [f"assumes {expected_clean_cycles(cfg)} major cycles: their number depends on the sky"]


COST = Cost(work, shrink="a smaller transfer.m_block", disk_shrink=disk_shrink, notes=notes,
            split=halvings("transfer.m_block"))
