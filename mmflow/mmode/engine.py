"""In-memory engine for one frequency: plan baseline chunks, build normal equations, solve.

These are the kernels the dask stages map over chunks (see :mod:`mmflow.workflow.stages`);
they are also usable directly on a laptop for small arrays.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmflow.conventions import m_slice, n_alm
from mmflow.imaging.solvers import solve_m
from mmflow.mmode.normal import NormalAccumulator
from mmflow.mmode.transfer import baselines_in_wavelengths, fringe_bandlimit, iter_transfer_blocks, make_grid


@dataclass
class BaselineChunk:
    """Baselines sharing one quadrature grid: indices into the telescope's pair list."""

    index: np.ndarray
    lmax: int


def plan_chunks(telescope, freq_hz, lmax, chunk_size=64, per_baseline_lmax=True):
    """Sort baselines by their lmax_b and cut them into chunks of ``chunk_size``.

    Chunks of short baselines get small grids: their cost scales like ``lmax_b^3``.
    """
    lmax_b = telescope.baseline_lmax(freq_hz, lmax) if per_baseline_lmax else np.full(
        len(telescope.antenna_pairs()), lmax)
    order = np.argsort(lmax_b, kind="stable")
    return [BaselineChunk(order[i:i + chunk_size], int(lmax_b[order[i:i + chunk_size]].max()))
            for i in range(0, len(order), chunk_size)], lmax_b


class GridCache:
    """Quadrature grids (and their Legendre tables) reused across chunks of one process.

    One grid at a time by default: at lmax 1000 a grid's float32 tables and workspace are
    ~2 GB. Chunks arrive sorted by per-baseline lmax, so grids are not rebuilt back and forth;
    the fringe band limit is rounded up to buckets of ``max(16, lmax / 8)`` so that
    neighbouring chunks share a grid (a grid at most ~12% larger than needed).
    """

    def __init__(self, telescope, freq_hz, max_items=1):
        self.telescope, self.freq_hz, self.max_items = telescope, freq_hz, max_items
        self._grids = {}

    def get(self, lmax, fringe_lmax):
        step = max(16, lmax // 8)
        fringe_lmax = int(step * np.ceil(fringe_lmax / step))
        key = (lmax, fringe_lmax)
        if key not in self._grids:
            if len(self._grids) >= self.max_items:
                self._grids.pop(next(iter(self._grids)))
            self._grids[key] = make_grid(self.telescope.lat_rad, self.telescope.beam, self.freq_hz,
                                         lmax, fringe_lmax)
        return self._grids[key]


def chunk_blocks(telescope, freq_hz, chunk, lmax, lmax_b, dtype=np.float64, cache=None, mmax=None, pad=True):
    """Yield ``(m, B_m)`` for one baseline chunk, columns ``l = m..lmax`` (``pad``) or ``m..chunk.lmax``.

    Blocks stop at ``m = chunk.lmax``: a chunk's coefficients vanish for larger m.
    """
    pairs = telescope.antenna_pairs()[chunk.index]
    b = baselines_in_wavelengths(telescope, pairs, freq_hz)
    cache = cache or GridCache(telescope, freq_hz)
    grid = cache.get(chunk.lmax, fringe_bandlimit(np.linalg.norm(b, axis=1), telescope.beam.lmax_hint))
    mmax = lmax if mmax is None else mmax
    for m, blk in iter_transfer_blocks(grid, b, lmax_b[chunk.index], min(mmax, chunk.lmax), dtype):
        if pad and chunk.lmax < lmax:
            full = np.zeros((blk.shape[0], lmax - m + 1), blk.dtype)
            full[:, :blk.shape[1]] = blk
            blk = full
        yield m, blk


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
                      on_block=None):
    """Add baseline chunks to ``acc``: the one streaming loop of the engine and the ``transfer`` stage.

    ``mmodes_of(chunk)`` returns the chunk's m-modes ``([n_split,] mmax + 1, 2, n)``;
    ``on_block(chunk, m, block)`` sees each (padded) transfer block (``transfer.mode=store``).
    """
    cache = cache or GridCache(telescope, freq_hz)
    for chunk in chunks:
        mm = mmodes_of(chunk)
        pad = on_block is not None
        for m, blk in chunk_blocks(telescope, freq_hz, chunk, acc.lmax, lmax_b, dtype, cache, acc.mmax, pad=pad):
            acc.add_mmodes(m, blk, mm, inv_var[chunk.index])
            if on_block is not None:
                on_block(chunk, m, blk)
    return acc


def accumulate_normal_equations(telescope, freq_hz, mmodes, lmax, inv_var=None, chunk_size=64,
                                dtype=np.float64, acc_dtype=None, per_baseline_lmax=True):
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
    acc_dtype = acc_dtype or (np.complex64 if np.dtype(dtype) == np.float32 else np.complex128)
    acc = NormalAccumulator(lmax, mm4.shape[1] - 1, acc_dtype, n_split=mm4.shape[0])
    w = np.ones(mm4.shape[3]) if inv_var is None else np.asarray(inv_var, float)
    return accumulate_chunks(acc, telescope, freq_hz, chunks, lmax_b, lambda c: mm4[..., c.index], w, dtype)


def solve_alm(acc, eps, method="tikhonov", filters=None, lmax=None, a_prior=None, split=0):
    """Solve every m block and assemble a healpy-layout alm vector (Jy/sr, frame of date).

    ``filters``: keyword arguments of :func:`mmflow.imaging.filters.filter_mask`; None applies
    the paper's defaults. Each m goes through :func:`mmflow.imaging.solvers.solve_m`, the same
    code as the workflow's ``solve`` stage. ``split`` picks the data split (0: full).
    """
    lmax = acc.lmax if lmax is None else lmax
    alm = np.zeros(n_alm(lmax), np.complex128)
    for m in acc.ms:
        prior = None if a_prior is None else a_prior[m_slice(lmax, m)]
        sol = solve_m(acc.full_gram(m), acc.rhs[m], m, lmax, method, eps, filters, prior)
        alm[m_slice(lmax, m)] = sol.alm[split]
    return alm
