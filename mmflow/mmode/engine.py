"""In-memory engine for one frequency: plan baseline chunks, build normal equations.

The solve of those equations is :func:`mmflow.imaging.solvers.solve_alm`.

These are the kernels the dask stages map over chunks (see :mod:`mmflow.workflow.stages`);
they are also usable directly on a laptop for small arrays.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from mmflow.conventions import complex_dtype
from mmflow.mmode.normal import NormalAccumulator
from mmflow.mmode.transfer import (baselines_in_wavelengths, fringe_bandlimit, iter_transfer_blocks, make_grid,
                                   transfer_pass)

#: A chunk's Fourier workspace (~ baselines x lmax_c^2) stays below that of ``chunk_size`` baselines
#: at ``max(lmax, REFERENCE_LMAX)``: chunks of shorter baselines hold more baselines (up to
#: ``MAX_CHUNK_FACTOR`` x ``chunk_size``); 64 baselines at lmax 1000 are ~1 GB in float32.
REFERENCE_LMAX = 1000
MAX_CHUNK_FACTOR = 16
#: A chunk's baselines span at most this ratio of per-baseline lmax (+2): its cost ~ n lmax^3.
CHUNK_LMAX_SPAN = 1.1


@dataclass
class BaselineChunk:
    """Baselines sharing one quadrature grid: indices into the telescope's pair list."""

    index: np.ndarray
    lmax: int


def plan_chunks(telescope, freq_hz, lmax, chunk_size=64, per_baseline_lmax=True, adaptive=True):
    """Sort baselines by their lmax_b and cut them into chunks of ``k * chunk_size`` baselines.

    A chunk's cost scales like ``n lmax_c^3`` and its Fourier workspace like ``n lmax_c^2``:
    chunks of short baselines (``adaptive``) take ``k = 1, 2, 4, .. MAX_CHUNK_FACTOR`` times
    ``chunk_size`` baselines while ``k lmax_c^2 <= max(lmax, REFERENCE_LMAX)^2`` and their
    lmax spans at most ``CHUNK_LMAX_SPAN`` (fewer, fatter GEMMs and Gram updates; about 1 %
    more flops than per-baseline chunks at the paper's channel). Sizes are multiples of
    ``chunk_size`` and depend only on the baselines and settings, never on the cluster.
    """
    lmax_b = telescope.baseline_lmax(freq_hz, lmax) if per_baseline_lmax else np.full(
        len(telescope.antenna_pairs()), lmax)
    if per_baseline_lmax:
        # by lmax_b, then by length: baselines capped at lmax share chunks with like fringe band limits
        order = np.lexsort((np.linalg.norm(telescope.baselines_enu(), axis=1), lmax_b))
    else:
        order = np.arange(len(lmax_b))  # one lmax: the telescope's own order
    sorted_lb = lmax_b[order]
    budget = float(max(lmax, REFERENCE_LMAX)) ** 2
    chunks, i, n = [], 0, len(order)
    while i < n:
        k = MAX_CHUNK_FACTOR if adaptive else 1
        while k > 1:
            last = sorted_lb[min(i + k * chunk_size, n) - 1]
            if k * float(last) ** 2 <= budget and last <= CHUNK_LMAX_SPAN * sorted_lb[i] + 2:
                break
            k //= 2
        j = min(i + k * chunk_size, n)
        chunks.append(BaselineChunk(order[i:j], int(sorted_lb[j - 1])))
        i = j
    return chunks, lmax_b


class GridCache:
    """Quadrature grids (and their Legendre tables) reused across chunks of one process.

    One grid at a time by default: at lmax 1000 a grid's float32 tables and workspace are
    ~2 GB. Chunks arrive sorted by per-baseline lmax, so grids are not rebuilt back and forth.
    A chunk's grid is built for its lmax rounded up to a multiple of ``max(16, lmax / 16)``
    (its blocks stop at the chunk's own lmax) and its fringe band limit rounded up to buckets
    of ``max(16, lmax / 8)``: neighbouring chunks share a grid and its tables (a grid at most
    ~12% larger than needed). ``build_s`` counts the seconds spent building grids.
    """

    def __init__(self, telescope, freq_hz, max_items=1, lmax=None):
        self.telescope, self.freq_hz, self.max_items, self.lmax = telescope, freq_hz, max_items, lmax
        self._grids = {}
        self.build_s = 0.0
        self.builds = 0

    @staticmethod
    def key(lmax, fringe_lmax, lmax_cap=None):
        """``(lmax, fringe_lmax)`` of the grid a chunk gets: both rounded up to their buckets (class docstring)."""
        cap = lmax if lmax_cap is None else lmax_cap
        step = max(16, cap // 16)
        lmax = min(cap, int(step * np.ceil(lmax / step)))
        fstep = max(16, cap // 8)
        return lmax, int(fstep * np.ceil(fringe_lmax / fstep))

    def get(self, lmax, fringe_lmax, lmax_cap=None):
        key = self.key(lmax, fringe_lmax, lmax_cap)
        lmax, fringe_lmax = key
        if key not in self._grids:
            if len(self._grids) >= self.max_items:
                self._grids.pop(next(iter(self._grids)))
            t0 = time.perf_counter()
            self._grids[key] = make_grid(self.telescope.lat_rad, self.telescope.beam, self.freq_hz,
                                         lmax, fringe_lmax)
            self.build_s += time.perf_counter() - t0
            self.builds += 1
        return self._grids[key]


def chunk_grid(telescope, freq_hz, chunk, lmax, cache):
    """A chunk's baselines in wavelengths (n, 3) and its quadrature grid from ``cache`` (band limit
    ``chunk.lmax``, fringe band limit of its longest baseline)."""
    b = baselines_in_wavelengths(telescope, telescope.antenna_pairs()[chunk.index], freq_hz)
    grid = cache.get(chunk.lmax, fringe_bandlimit(np.linalg.norm(b, axis=1), telescope.beam.lmax_hint), lmax)
    return b, grid


def chunk_blocks(telescope, freq_hz, chunk, lmax, lmax_b, dtype=np.float64, cache=None, mmax=None, pad=True):
    """Yield ``(m, B_m)`` for one baseline chunk, columns ``l = m..lmax`` (``pad``) or ``m..chunk.lmax``.

    Blocks stop at ``m = chunk.lmax``: a chunk's coefficients vanish for larger m.
    """
    cache = cache or GridCache(telescope, freq_hz)
    b, grid = chunk_grid(telescope, freq_hz, chunk, lmax, cache)
    mmax = lmax if mmax is None else mmax
    for m, blk in iter_transfer_blocks(grid, b, lmax_b[chunk.index], min(mmax, chunk.lmax), dtype,
                                       lmax_rows=chunk.lmax):
        if pad and chunk.lmax < lmax:
            full = np.zeros((blk.shape[0], lmax - m + 1), blk.dtype)
            full[:, :blk.shape[1]] = blk
            blk = full
        yield m, blk


def add_chunk(acc, telescope, freq_hz, chunk, lmax_b, mmodes, inv_var, dtype, cache, timings=None):
    """Add one baseline chunk to ``acc`` with the fused per-m step of :func:`transfer_pass`.

    For each m one pool task computes ``B_m`` (Legendre GEMMs), masks ``l > lmax_b`` and weights
    rows by ``sqrt(w)`` in one pass, then ``G_m += B^H W B`` (one ``herk`` straight into the
    Gram's leading sub-block) and ``r_m += B^H W v``; ``v^H W v`` for all m at once.

    ``mmodes``: the chunk's ``(n_split, mmax + 1, 2, n)``; ``inv_var``: its ``(n,)`` weights.
    """
    t0 = time.perf_counter()
    built = cache.build_s
    b, grid = chunk_grid(telescope, freq_hz, chunk, acc.lmax, cache)
    if timings is not None:
        timings["grid_s"] = timings.get("grid_s", 0.0) + cache.build_s - built
    nb = len(chunk.index)
    mtop = min(acc.mmax, chunk.lmax)
    w = np.asarray(inv_var, float)
    sw = np.sqrt(w)
    mm = np.asarray(mmodes)[:, :mtop + 1]
    # data rows V_m then conj(V_{-m}) (see NormalAccumulator.add_mmodes), times sqrt(w)
    vw = (mm * sw).astype(acc.dtype).reshape(mm.shape[0], mtop + 1, 2 * nb)

    def consume(m, out, tim):
        rows = nb if m == 0 else 2 * nb
        acc.add_scaled_block(m, out, rows, out.shape[0], vw[:, m, :rows], tim)

    transfer_pass(grid, b, consume, lmax_b[chunk.index], mtop, dtype, chunk.lmax, sw, timings)
    p = np.abs(mm) ** 2 @ w  # (n_split, m, 2)
    p[:, 0, 1] = 0.0
    acc.vhv[:, :mtop + 1] += p.sum(axis=2)
    if timings is not None:
        timings["chunk_s"] = timings.get("chunk_s", 0.0) + time.perf_counter() - t0
        timings["chunks"] = timings.get("chunks", 0) + 1


def plan_groups(chunks, n_groups):
    """Cut the (lmax-sorted) chunks into ``n_groups`` contiguous runs of balanced cost ``~ n lmax_b^3``.

    The grouping depends only on the chunks and ``n_groups`` (a setting), never on the
    cluster, so partial sums and their fixed-order reduction are the same on any cluster.
    """
    n_groups = max(1, min(len(chunks), n_groups))
    cost = np.cumsum([len(c.index) * float(c.lmax) ** 3 for c in chunks])
    cut = np.searchsorted(cost, cost[-1] * np.arange(1, n_groups) / n_groups)
    bounds = np.concatenate([[0], cut, [len(chunks)]])
    return [chunks[bounds[k]:bounds[k + 1]] for k in range(n_groups) if bounds[k + 1] > bounds[k]]


def accumulate_chunks(acc, telescope, freq_hz, chunks, lmax_b, mmodes_of, inv_var, dtype, cache=None,
                      on_block=None, timings=None, progress=None):
    """Add baseline chunks to ``acc``: the one streaming loop of the engine and the ``transfer`` stage.

    ``mmodes_of(chunk)`` returns the chunk's m-modes ``([n_split,] mmax + 1, 2, n)``;
    ``on_block(chunk, m, block)`` sees each (padded) transfer block (``transfer.mode=store``);
    ``timings`` accumulates per-phase seconds (see :func:`add_chunk`); ``progress(i, n, chunk)``
    is called after each chunk.
    """
    cache = cache or GridCache(telescope, freq_hz)
    for i, chunk in enumerate(chunks):
        mm = np.asarray(mmodes_of(chunk))
        mm4 = mm if mm.ndim == 4 else mm[None]
        if on_block is None:
            add_chunk(acc, telescope, freq_hz, chunk, lmax_b, mm4, inv_var[chunk.index], dtype, cache, timings)
        else:
            for m, blk in chunk_blocks(telescope, freq_hz, chunk, acc.lmax, lmax_b, dtype, cache, acc.mmax):
                acc.add_mmodes(m, blk, mm4, inv_var[chunk.index])
                on_block(chunk, m, blk)
        if progress is not None:
            progress(i, len(chunks), chunk)
    return acc


def accumulate_normal_equations(telescope, freq_hz, mmodes, lmax, inv_var=None, chunk_size=64,
                                dtype=np.float64, acc_dtype=None, per_baseline_lmax=True, timings=None):
    """Stream over baseline chunks: ``G_m += B^H N^-1 B``, ``r_m += B^H N^-1 v``, ``v^H N^-1 v``.

    Parameters
    ----------
    mmodes : ndarray ([n_split,] mmax + 1, 2, n_bl)
    inv_var : ndarray (n_bl,), optional
        Inverse noise variance of each baseline's m-modes (same for all m).
    """
    mmodes = np.asarray(mmodes)
    mm4 = mmodes if mmodes.ndim == 4 else mmodes[None]
    chunks, lmax_b = plan_chunks(telescope, freq_hz, lmax, chunk_size, per_baseline_lmax)
    acc_dtype = acc_dtype or complex_dtype(dtype).type
    acc = NormalAccumulator(lmax, mm4.shape[1] - 1, acc_dtype, n_split=mm4.shape[0])
    w = np.ones(mm4.shape[3]) if inv_var is None else np.asarray(inv_var, float)
    return accumulate_chunks(acc, telescope, freq_hz, chunks, lmax_b, lambda c: mm4[..., c.index], w, dtype,
                             timings=timings)
