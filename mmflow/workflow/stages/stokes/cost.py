"""The stokes stage's cost: a task per channel holding the whole channel's Gram over [T, E, B, V]
(complex128, full matrices) and its Cholesky factors, one set for the solve, the leakage and the CLEAN of
V (two Grams), and the ring FFTs of one pass of at most 64 baselines (16 fields x (+m, -m) per ring and
m, complex128, ~lmax / 2 north rings), in m-blocks within ``FOURIER_BUDGET_BYTES``."""
from __future__ import annotations

from mmflow.io import run_stores as rs
from mmflow.mmode.polarised_transfer import FOURIER_BUDGET_BYTES
from mmflow.workflow.plan.work import (COMPLEX128_BYTES, PSF_DECLINATIONS, Cost, Work, expected_clean_cycles)

#: Grams held at once: the solve's and its factors (the leakage and the CLEAN of V reuse them)
GRAMS = 2
#: baselines of one pass of the ring FFTs
PASS_BASELINES = 64


def work(g, cfg):
    gram = GRAMS * COMPLEX128_BYTES * sum((4 * (g.lmax - m + 1)) ** 2 for m in range(g.lmax + 1))
    coef = min(FOURIER_BUDGET_BYTES,
               2 * 16 * 2 * PASS_BASELINES * COMPLEX128_BYTES * (g.lmax + 1) * (g.lmax // 2 + 2))
    c = cfg.clean  # the CLEAN of V: components and peaks are written for the cycles run
    spec = rs.stokes_store(g.n_split, g.n_freq, g.lmax, g.mmax,
                           (PSF_DECLINATIONS, expected_clean_cycles(cfg), c.peaks_per_cycle) if c.enabled else None)
    return Work(g.n_freq, gram + coef, g.n_bl * 4 * (g.lmax + 1) ** 2, [spec])


COST = Cost(work, shrink="a smaller chunk")
