"""In-memory engine for one frequency: plan baseline chunks, build normal equations, solve.

These are the kernels the dask stages map over chunks (see :mod:`mmflow.workflow.stages`);
they are also usable directly on a laptop for small arrays.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmflow.conventions import m_slice, n_alm
from mmflow.imaging.filters import filter_mask
from mmflow.imaging.solvers import solve_block
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


def accumulate_normal_equations(telescope, freq_hz, mmodes, lmax, inv_var=None, chunk_size=64,
                                dtype=np.float64, acc_dtype=None, per_baseline_lmax=True):
    """Stream over baseline chunks: ``G_m += B^H N^-1 B``, ``r_m += B^H N^-1 v``, ``v^H N^-1 v``.

    Parameters
    ----------
    mmodes : ndarray (mmax + 1, 2, n_bl)
    inv_var : ndarray (n_bl,), optional
        Inverse noise variance of each baseline's m-modes (same for all m).
    """
    mmax = mmodes.shape[0] - 1
    chunks, lmax_b = plan_chunks(telescope, freq_hz, lmax, chunk_size, per_baseline_lmax)
    acc_dtype = acc_dtype or (np.complex64 if np.dtype(dtype) == np.float32 else np.complex128)
    acc = NormalAccumulator(lmax, mmax, acc_dtype)
    cache = GridCache(telescope, freq_hz)
    w = np.ones(mmodes.shape[2]) if inv_var is None else np.asarray(inv_var, float)
    for chunk in chunks:
        mm, wc = mmodes[..., chunk.index], w[chunk.index]
        for m, blk in chunk_blocks(telescope, freq_hz, chunk, lmax, lmax_b, dtype, cache, mmax, pad=False):
            acc.add_mmodes(m, blk, mm, wc)
    return acc


def solve_alm(acc, eps, method="tikhonov", filters=None, lmax=None, a_prior=None):
    """Solve every m block and assemble a healpy-layout alm vector (Jy/sr, frame of date).

    ``filters``: keyword arguments of :func:`mmflow.imaging.filters.filter_mask`; None applies
    the paper's defaults. Filtered coefficients are removed from the unknowns before solving.
    """
    lmax = acc.lmax if lmax is None else lmax
    filters = {} if filters is None else filters
    alm = np.zeros(n_alm(lmax), np.complex128)
    for m in acc.ms:
        keep = filter_mask(m, lmax, **filters)
        if not keep.any():
            continue
        g = acc.full_gram(m)[np.ix_(keep, keep)]
        r = acc.rhs[m][keep]
        prior = None if a_prior is None else a_prior[m_slice(lmax, m)][keep]
        sol = solve_block(method, g, r, eps, ell=np.arange(m, lmax + 1)[keep], a_prior=prior)
        block = np.zeros(lmax - m + 1, np.complex128)
        block[keep] = sol
        alm[m_slice(lmax, m)] = block
    return alm
