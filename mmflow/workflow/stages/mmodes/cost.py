"""The mmodes stage's cost: a task per baseline chunk holding the corrected block of every integration and,
per channel, fitting the m-modes of Stokes I and then (full Stokes) of each of the four correlations into
outputs it holds; its peak is the larger of the read (with peeling on, the peel's correction of one channel:
:func:`mmflow.workflow.plan.work.read_bytes`) and the fits::

    W = max(read, block + max(n_time bc n_freq 24 + out + max(fit, ZARR_WRITE_COPIES out),
                              4 out + max(n_time bc 24 + fit, ZARR_WRITE_COPIES 4 out)))
    out = n_split n_freq (mmax + 1) 2 bc 16
    fit = n_bins bc 24 + fit_bytes(n_bins, k_max, n_split, mmax, bc)

(``block``: :func:`mmflow.workflow.plan.work.block_bytes`; the Stokes-I copy of every channel, or one
correlation's integrations of one channel; zarr's encoded copy of the m-modes as they are written,
:data:`~mmflow.workflow.plan.work.ZARR_WRITE_COPIES`; one channel's sidereal bins and weights and the temporaries of
:func:`mmflow.mmode.gapfill.chunk_mmodes`, by the bins and by the band ``k_max`` it fits: :func:`fit_bytes`,
:func:`band_max`)."""
from __future__ import annotations

from mmflow.conventions import FULL_STOKES, is_full_stokes
from mmflow.io import run_stores as rs
from mmflow.workflow.engine.geometry import fit_band, fit_bins
from mmflow.workflow.plan.work import (COMPLEX128_BYTES, CORRECTED_SAMPLE_BYTES, ZARR_WRITE_COPIES, Cost, Work,
                                       block_bytes, four_correlation_note, halvings, read_bytes)

#: a fit's phases, each as complex (bin, baseline) and (band, baseline) arrays alive at once
#: (:func:`mmflow.mmode.gapfill.lsq_mmodes`, per ``n_bins`` bins and ``k = 2 k_max + 1`` m's of its band): while it
#: forms the right-hand side (the data, the weights, their weighted product, its transposed copy and transform,
#: beside the Toeplitz spectrum of about ``2 k``), and while it iterates (the data and weights kept; the Toeplitz
#: spectrum, the conjugate-gradient vectors and a product's transforms)
FIT_PHASES = ((4.5, 3.0), (1.7, 14.0))
#: the earlier splits' m-modes a fit holds while it runs, in units of every split's m-modes of one channel
FIT_HELD_OUTPUTS = 0.2
#: every split's m-modes as :func:`mmflow.mmode.gapfill.split_lsq_mmodes` returns them: the list and its stack
FIT_STACKED_OUTPUTS = 2.2
# fitted to the tracemalloc peaks of chunk_mmodes (full, even, odd) at 29 points of bins 512-2048, k_max 14-511
# and mmax 100-400: within -6 / +8 % (benchmarks/mmode_fit_memory.py)


#: a full-Stokes task's time over the plan's Stokes-I task: the m-modes of each of the four correlations besides
#: Stokes I's, and with an E-field beam the peeled sources' four correlations re-formed on read. Measured on the
#: paper's channel (2026-12-02, 256 antennas, 2 workers on this VM's 2 cores, nothing else running): 68 tasks,
#: median 16.2 s, against the plan's 2.86 s for the Stokes-I task at 191 SGEMM GFLOP/s (the Stokes-I night run
#: measured 3.6-3.9 s: 4.3x). ``benchmarks/four_correlation_ratio.py`` at 64 antennas over a whole day gave 3.76 in
#: one process: the four correlations' work per baseline grows with the array in a way not yet traced
#: (docs/stokes.md)
FOUR_CORRELATION_TIME = 5.7


def work(g, cfg):
    bc = min(g.mmode_chunk, g.n_bl)
    full = is_full_stokes(cfg.imaging.stokes)
    out = g.n_split * g.n_freq * (g.mmax + 1) * 2 * bc * COMPLEX128_BYTES
    fit = g.n_bins * bc * CORRECTED_SAMPLE_BYTES + fit_bytes(g.n_bins, band_max(g, cfg), g.n_split, g.mmax, bc)
    # Stokes I: its copy of the data and its m-modes, while it fits or writes them
    held = g.n_time * bc * g.n_freq * CORRECTED_SAMPLE_BYTES + out + max(fit, ZARR_WRITE_COPIES * out)
    if full:  # the four correlations' m-modes while it fits one correlation's integrations of a channel, or writes
        c_out = len(FULL_STOKES) * out
        held = max(held, c_out + max(g.n_time * bc * CORRECTED_SAMPLE_BYTES + fit, ZARR_WRITE_COPIES * c_out))
    w = max(read_bytes(g, cfg, g.n_time, bc, g.n_freq), block_bytes(g, g.n_time, bc, g.n_freq, full) + held)
    spec = rs.mmodes_store(g.n_split, g.n_freq, g.mmax, g.n_bl, g.mmode_chunk, {}, len(FULL_STOKES) if full else 0)
    return Work(-(-g.n_bl // bc), w, g.n_time * bc * g.n_freq * g.n_pol * (FOUR_CORRELATION_TIME if full else 1.0),
                [spec])


def notes(g, cfg, peak_gflops):
    return [four_correlation_note(FOUR_CORRELATION_TIME)] if is_full_stokes(cfg.imaging.stokes) else []


def fit_bytes(n_bins, k_max, n_split, mmax, n_bl):
    """Peak bytes of :func:`mmflow.mmode.gapfill.chunk_mmodes` fitting ``n_split`` splits of ``n_bins`` bins of
    ``n_bl`` baselines up to band ``k_max`` (``mmax``: the m-modes it returns), its largest phase::

        16 n_bl max(max_(a, b in FIT_PHASES) (a n_bins + b k) + FIT_HELD_OUTPUTS o, FIT_STACKED_OUTPUTS o)
        k = 2 k_max + 1,  o = n_split (mmax + 1) 2"""
    k, o = 2 * k_max + 1, n_split * (mmax + 1) * 2
    fitting = max(a * n_bins + b * k for a, b in FIT_PHASES) + FIT_HELD_OUTPUTS * o
    return COMPLEX128_BYTES * n_bl * max(fitting, FIT_STACKED_OUTPUTS * o)


def band_max(g, cfg):
    """The widest fit's band limit ``k_max``: the longest baseline's at the highest channel, at most half the
    bins the smallest split fits (:func:`mmflow.workflow.engine.geometry.fit_band`), as the stage fits it."""
    n_fit = fit_bins(cfg.mmode.splits, g.n_bins)
    return max(int(fit_band(g.tel, f, n_fit).max()) for f in g.freqs_hz)


COST = Cost(work, shrink="a smaller mmode.baseline_chunk", split=halvings("mmode.baseline_chunk"), notes=notes)
