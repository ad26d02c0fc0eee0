"""The stokes stage's cost: per channel a task per block of m (:func:`blocks.blocks_of`) and one task of the
second phase; the time from the work the stage does, counted as the stage does it, at rates measured on one
thread by ``mmflow bench stokes-block`` (there are no fitted constants for it).

A block task holds its block's Grams in the accumulation's precision (each m's complex128 Gram and factor made
and dropped in turn), its m-modes (in that precision too, read a store chunk at a time), one pass's ring-Fourier
arrays (at most ``FOURIER_BUDGET_BYTES``) and the largest chunk grid's feed responses. Its thread-seconds
(:func:`block_parts`):

* ``grid``: each chunk grid made (consecutive chunks share one), its points at ``GRID_SECONDS_PER_POINT``;
* ``ring``: ring products and FFTs: for every chunk of baselines (sorted by per-baseline lmax, as the stage
  chunks them), the points of the chunk's grid x 16 kernels x baselines, once per Fourier block of the m it
  covers (:func:`mmflow.mmode.polarised_transfer.fourier_m_block`; above the polarised band limit the I
  kernels alone in blocks of 4x the m, ``RING_I_ONLY`` of a pass), at ``RING_SECONDS_PER_POINT``: every block of
  m pays it again;
* ``gemm``: Legendre GEMMs (``lambda`` on I and V to the chunk's top, ``W``, ``X`` on Q, U to the polarised band
  limit) and the ``herk`` of ``4 x 2 n_b`` rows into ``N_m^2`` (``4 k N^2`` flops) at ``GEMM_EFFICIENCY`` of a
  core's SGEMM peak;
* ``factor``: the Cholesky factors (``8 N^3 / 3``) at ``FACTOR_EFFICIENCY`` of a core's peak (complex128, BLAS
  on one thread as in every task),

over the task's threads (its ring and m pools; the factors on one). A core's peak is the SGEMM peak over
:func:`mmflow.threads.usable_cores`. The second phase factorises every m once more for the polarisation
response and, for the m whose factors are not kept (all are where a channel's fit ``KEPT_BYTES``, else the
largest within ``FACTORS_KEPT_BYTES``, :func:`blocks.factors_kept`), again for each pass of the response tables
(``DECS_PER_PASS`` declinations a pass) and each cycle of the CLEAN of the sources (always; one more for its
closing step, :func:`mmflow.imaging.polarised_clean.close_sources`) and of V (``clean.enabled``; the plan assumes
``EXPECTED_CLEAN_CYCLES`` each).
"""
from __future__ import annotations

import ducc0
import numpy as np

from mmflow.io import run_stores as rs
from mmflow.imaging.polarised import BLOCK_BYTES_PER_ELEMENT
from mmflow.imaging.polarised_clean import DECS_PER_PASS
from mmflow.mmode.polarised import CORRELATIONS
from mmflow.mmode.polarised_transfer import (FOURIER_BUDGET_BYTES, PASS_BASELINES, fourier_bytes, legendre_rows,
                                             m_block_of, pass_baselines)
from mmflow.mmode.transfer import baselines_in_wavelengths, fringe_bandlimit
from mmflow.mmode.engine import GridCache
from mmflow.threads import usable_cores
from mmflow.workflow.engine.geometry import stokes_lmax_of
from mmflow.workflow.plan.work import (COMPLEX128_BYTES, EXPECTED_CLEAN_CYCLES, PSF_DECLINATIONS, Cost, Work,
                                      expected_clean_cycles)
from mmflow.workflow.stages.stokes.blocks import (blocks_of, factor_sizes_of, factors_kept, gram_dtype,
                                                 gram_itemsize, kept_in_memory, mmode_bytes_per_m, sizes_of)

#: thread-seconds per ring point, kernel, baseline and Fourier block (:func:`polarised_fourier`'s fringes, folds,
#: FFTs and copies, the short dipole's 10 distinct kernels of 16 transformed) at a core's SGEMM peak
#: ``REFERENCE_CORE_GFLOPS``, and the I kernels' passes above the polarised band limit as a fraction of a pass of
#: every kernel: ``mmflow bench stokes-block`` (docs/stokes.md, 2026-12-03), the paper's channel, 1/128 of its
#: baselines, its five blocks of m on one thread, the two constants fitted to their ring seconds (within 21 %
#: each); the reference the geometric mean of the run's SGEMM peaks before and after (295 and 218) over 2 cores
RING_SECONDS_PER_POINT = 8.44e-9
RING_I_ONLY = 0.50
REFERENCE_CORE_GFLOPS = 126.9
#: fraction of a core's SGEMM peak the Legendre GEMMs, ``herk`` and right-hand sides run at on one thread (the
#: same run: 1.96e12 flops in 45.8 s; 0.25-0.38 by block, the wider blocks of m faster)
GEMM_EFFICIENCY = 0.34
#: fraction of a core's SGEMM peak the solve runs its complex128 Cholesky factors at on one thread (the same run:
#: 1.80e12 flops, ``8 N^3 / 3`` a factor, in 32.6 s, the solves and the leakage's Gram products included)
FACTOR_EFFICIENCY = 0.44
#: thread-seconds per point of a chunk's polarised grid (:func:`mmflow.mmode.polarised.make_polarised_grid`)
#: at the reference (the same run: 22.6 s for 3.32e7 points)
GRID_SECONDS_PER_POINT = 6.8e-7
#: kernels of the ring stage: I, V, Q, U for each of the four correlations
KERNELS = 4 * len(CORRELATIONS)
#: test sources of the polarisation response (4 at each of up to 5 declinations: the stokes stage's)
RESPONSE_SOURCES = 20


def _grid_shape(top, fringe):
    """``(n_theta, n_phi)`` of a chunk's grid (:func:`mmflow.mmode.polarised.make_polarised_grid`)."""
    quad = top + fringe
    n_theta = quad // 2 + 2
    n_theta += n_theta % 2
    return n_theta, ducc0.fft.good_size(max(quad + 2, 2 * top + 2))


def _baselines(g, cfg):
    """One channel's baselines as the stage orders them: ``(order, lmax_b, |b| in wavelengths, rings of the
    largest grid)`` (sorted by per-baseline lmax; the largest grid is that of every baseline at lmax)."""
    tel, f, lmax = g.tel, g.freqs_hz[-1], g.lmax
    pairs = tel.antenna_pairs()
    b_len = np.linalg.norm(baselines_in_wavelengths(tel, pairs, f), axis=1)
    lb = tel.baseline_lmax(f, lmax, pairs) if cfg.transfer.per_baseline_lmax else np.full(len(pairs), lmax)
    n_theta, _ = _grid_shape(*GridCache.key(lmax, fringe_bandlimit(b_len, tel.beam.lmax_hint), lmax))
    return np.argsort(lb, kind="stable"), lb, b_len, n_theta


def _chunks(g, cfg, baselines, m_range, lmax_p):
    """Per chunk of baselines ``(n_b, top, grid points, lmax_b array)`` as the stage chunks one channel's block
    of m ``m_range`` (:func:`_baselines`): :func:`mmflow.mmode.polarised_transfer.pass_baselines` a chunk."""
    order, lb, b_len, n_theta = baselines
    m0, m1 = m_range
    n_pol_m = max(0, min(m1, lmax_p + 1) - m0)
    per_m = fourier_bytes(n_theta // 2, 1, len(CORRELATIONS), gram_itemsize(cfg))
    per = pass_baselines(per_m, n_pol_m, m1 - m0 - n_pol_m)
    out = []
    for s in range(0, len(order), per):
        idx = order[s:s + per]
        top = int(lb[idx].max())
        key = GridCache.key(top, fringe_bandlimit(b_len[idx], g.tel.beam.lmax_hint), g.lmax)
        out.append((len(idx), top, _grid_shape(*key), lb[idx]))
    return out


def block_parts(g, cfg, baselines, m0, m1, size, lmax_p, core_gflops):
    """Thread-seconds of one block task ``(m0, m1)`` by part (module docstring): ``{"grid", "ring", "gemm",
    "factor"}`` at a core's SGEMM peak ``core_gflops``, for ``baselines`` (:func:`_baselines`, or a subset)."""
    ring = flops = grid_pts = 0.0
    last = None
    for nb, top, (n_theta, n_phi), lbs in _chunks(g, cfg, baselines, (m0, m1), lmax_p):
        if top < m0:
            continue
        if (n_theta, n_phi) != last:  # a new grid (the stage keeps the last one)
            grid_pts += n_theta * n_phi
            last = (n_theta, n_phi)
        n_act = n_theta // 2
        m_hi = min(top, m1 - 1)
        step = m_block_of(fourier_bytes(n_act, nb, len(CORRELATIONS), gram_itemsize(cfg)))
        n_pol_m = max(0, min(m_hi, lmax_p) - m0 + 1)  # every kernel; above lmax_p the I kernels alone
        n_i_m = m_hi - m0 + 1 - n_pol_m
        points = n_act * 2 * n_phi * KERNELS * nb  # a pass of every kernel over the chunk's grid
        ring += points * (-(-n_pol_m // step) + RING_I_ONLY * -(-n_i_m // (4 * step)))
        for m in range(m0, m_hi + 1):
            cols = nb if m == 0 else 2 * nb
            n_t, n_p = top - m + 1, max(0, min(top, lmax_p) - m + 1)
            flops += 2.0 * n_act * legendre_rows(n_t, n_p) * len(CORRELATIONS) * cols * 2
            flops += 4.0 * len(CORRELATIONS) * cols * (n_t + 3 * n_p) ** 2  # herk
    slow = REFERENCE_CORE_GFLOPS / core_gflops
    return {"grid": grid_pts * GRID_SECONDS_PER_POINT * slow, "ring": ring * RING_SECONDS_PER_POINT * slow,
            "gemm": flops / (GEMM_EFFICIENCY * core_gflops * 1e9),
            "factor": _factor_seconds(factor_sizes_of(cfg), m0, m1, core_gflops)}


def _factor_seconds(size, m0, m1, core_gflops):
    """Thread-seconds of the Cholesky factors of m in ``[m0, m1)`` (``8 N^3 / 3`` each)."""
    return sum(8.0 * float(size(m)) ** 3 / 3 for m in range(m0, m1)) / (FACTOR_EFFICIENCY * core_gflops * 1e9)


def block_seconds(parts, threads):
    """A block task's wall seconds from :func:`block_parts`: the factors on one thread, the rest on ``threads``."""
    return (parts["grid"] + parts["ring"] + parts["gemm"]) / max(1, threads) + parts["factor"]


def core_gflops(peak):
    """A core's SGEMM peak from the machine's (``peak`` over :func:`mmflow.threads.usable_cores`)."""
    return peak / usable_cores()


def _plan(g, cfg):
    size, lmax_p = sizes_of(cfg), stokes_lmax_of(cfg)
    blocks = blocks_of(cfg, g.n_split, g.n_bl)
    # the block's Grams in the accumulation's precision, and one m's complex128 Gram and factor (and the copy of
    # its kept unknowns) while it is solved (:meth:`PolarisedObserver.solution_and_leakage`)
    gram = [gram_itemsize(cfg) * sum(float(size(m)) ** 2 for m in range(m0, m1))
            + (2 * COMPLEX128_BYTES + gram_itemsize(cfg)) * float(size(m0)) ** 2 for m0, m1 in blocks]
    mm = [mmode_bytes_per_m(cfg, g.n_split, g.n_bl) * (m1 - m0) for m0, m1 in blocks]
    all_gram = sum(float(size(m)) ** 2 for m in range(g.lmax + 1)) * COMPLEX128_BYTES
    kept = kept_in_memory(cfg)
    return size, lmax_p, blocks, gram, mm, all_gram, kept


def work(g, cfg):
    size, lmax_p, blocks, gram, mm, all_gram, kept = _plan(g, cfg)
    n_theta, n_phi = _grid_shape(g.lmax, g.lmax)
    grid = 2 * 2 * n_theta * n_phi * COMPLEX128_BYTES  # feeds x (N, E) responses of the largest grid
    # one pass's Fourier arrays (polarised_fourier: 2 x 2 x rings x 2 x corr x 2 n_b per m), at most the budget
    fourier = min(FOURIER_BUDGET_BYTES, fourier_bytes(n_theta // 2, min(PASS_BASELINES[1], g.n_bl), len(CORRELATIONS),
                                                      gram_itemsize(cfg)) * (g.lmax + 1))
    # the store chunk being read, complex128 and every m (:func:`stage._block_mmodes`)
    chunk = COMPLEX128_BYTES * g.n_split * (g.mmax + 1) * 2 * len(CORRELATIONS) * min(g.mmode_chunk, g.n_bl)
    block_task = max(a + b for a, b in zip(gram, mm)) + fourier + grid + chunk
    # the second phase: the Grams and factors (or one m's Gram and factor), the splits' harmonics and the test sources'
    # (the polarisation response's 4 per declination, or a pass of a response table's) imaged: in and out, T, E,
    # B, V each; the response table's PSF columns (one of the four, every declination)
    n_alm = (g.lmax + 1) * (g.lmax + 2) / 2
    vectors = 2 * max(RESPONSE_SOURCES, 4 * DECS_PER_PASS) + g.n_split + PSF_DECLINATIONS / 4
    factor_size = factor_sizes_of(cfg)
    held = (BLOCK_BYTES_PER_ELEMENT * all_gram / COMPLEX128_BYTES if kept else 2 * COMPLEX128_BYTES * size(0) ** 2
            + COMPLEX128_BYTES * sum(float(factor_size(m)) ** 2 for m in factors_kept(cfg)))  # + the factors kept
    second = held + vectors * 4 * n_alm * COMPLEX128_BYTES
    c = cfg.clean  # the CLEANs of the sources and of V: components and peaks are written for the cycles run
    spec = rs.stokes_store(g.n_split, g.n_freq, g.lmax, g.mmax,
                           (PSF_DECLINATIONS, expected_clean_cycles(cfg), c.peaks_per_cycle) if c.enabled else None,
                           blocks, lmax_p, gram_dtype(cfg),
                           (PSF_DECLINATIONS, min(c.max_cycles, EXPECTED_CLEAN_CYCLES), c.peaks_per_cycle))
    units = sum(float(size(m)) ** 2 for m in range(g.lmax + 1)) * g.n_bl
    return Work(g.n_freq * (len(blocks) + 1), max(block_task, second), units, [spec])


def seconds(g, cfg, per_task, workers, peak):
    """The stage's wall time: each channel's block tasks in rounds over the task slots, then its second
    phase (module docstring)."""
    size, lmax_p, blocks, *_, kept = _plan(g, cfg)
    baselines, core = _baselines(g, cfg), core_gflops(peak)
    block_s = sorted((block_seconds(block_parts(g, cfg, baselines, m0, m1, size, lmax_p, core), g.task_threads)
                      for m0, m1 in blocks), reverse=True)
    # the block tasks of all channels over the slots (each channel's blocks alike), longest first
    per_slot = [0.0] * max(1, workers)
    for s in block_s * g.n_freq:
        per_slot[per_slot.index(min(per_slot))] += s
    factor_size = factor_sizes_of(cfg)  # the m-filters' unknowns removed (m = 0: none factorised)
    factor_s = _factor_seconds(factor_size, 0, g.lmax + 1, core)
    # the factors not kept (none when all fit), made again per observation
    again = 0.0 if kept else factor_s - sum(_factor_seconds(factor_size, m, m + 1, core) for m in factors_kept(cfg))
    # the response; unless kept, the response tables' passes (the sources', and V's with clean.enabled) and cycles
    tables = (1 + bool(cfg.clean.enabled)) * -(-PSF_DECLINATIONS // DECS_PER_PASS)
    cycles = min(cfg.clean.max_cycles, EXPECTED_CLEAN_CYCLES) + 1 + expected_clean_cycles(cfg)  # + sources' closing
    second = (factor_s + again * (tables + cycles)) * -(-g.n_freq // max(1, workers))
    return max(per_slot) + second


def notes(g, cfg, peak):
    size, lmax_p, blocks, gram, mm, all_gram, kept = _plan(g, cfg)
    whole = f"a channel's whole Gram {all_gram / 1e9:.2f} GB (complex128)"
    split = (f"{len(blocks)} blocks of m a channel, {whole} in none of them" if len(blocks) > 1 else
             f"one block of m a channel ({whole})")
    return [f"Q, U, V to l = {lmax_p} (imaging.stokes_lmax), I to {g.lmax}; {split}"]


COST = Cost(work, shrink="a lower imaging.stokes_lmax (Q, U, V's band limit: the Gram grows as (lmax + 3 "
            "stokes_lmax)^3)", seconds=seconds, notes=notes)
