"""The stokes stage's blocks of m and the sizes of its normal equations (the stage's and its cost model's)."""
from __future__ import annotations

import numpy as np

from mmflow.conventions import complex_dtype
from mmflow.imaging.filters import filter_mask
from mmflow.imaging.polarised import BLOCK_BYTES_PER_ELEMENT, stokes_m_blocks, stokes_sizes
from mmflow.mmode.polarised import CORRELATIONS
from mmflow.workflow.engine.geometry import stokes_lmax_of
from mmflow.workflow.engine.kernel_args import m_filters

#: bytes of a phase-one task's Grams (the accumulation's precision: each m is factorised on its own) and m-modes
#: (:func:`stokes_m_blocks`): with the ring FFTs' budget and the grid, a task of about 5.5 GB. Every block of m
#: pays the ring stage (the FFTs of the fringes times the kernels) of every baseline again, so fewer, larger
#: blocks are faster: at the paper's scale 3 blocks with the m-modes in the transfer's precision (5 with them
#: complex128, 10 with 3 GB of complex128 Grams and factors: docs/stokes.md)
BLOCK_BYTES = 4 * 2 ** 30
#: phase two keeps a channel's Grams and their Cholesky factors in memory when they fit this (each Gram read
#: once; else it reads and factorises each stored Gram again per observation: the same bits, one m's matrices
#: in memory)
KEPT_BYTES = 2 ** 31


def mmode_bytes_per_m(cfg, n_split, n_bl):
    """Bytes of one m's m-modes of the four correlations as a block task holds them (+m and -m, every split, in
    the transfer's precision: complex64 for ``transfer.dtype: float32``, half the store's complex128)."""
    return n_split * 2 * len(CORRELATIONS) * n_bl * gram_itemsize(cfg)


def blocks_of(cfg, n_split, n_bl):
    """The stage's blocks of m ``[(m0, m1), ...]``: from the settings and the data's size only."""
    return stokes_m_blocks(cfg.mmode.lmax, stokes_lmax_of(cfg), BLOCK_BYTES, mmode_bytes_per_m(cfg, n_split, n_bl),
                           gram_itemsize(cfg))


def sizes_of(cfg):
    """``m -> N_m``, the unknowns ``[T; E; B; V]`` of block m (:func:`stokes_sizes`)."""
    lmax, lmax_p = cfg.mmode.lmax, stokes_lmax_of(cfg)

    def size(m):
        n_t, n_p = stokes_sizes(m, lmax, lmax_p)
        return n_t + 3 * n_p
    return size


def factor_sizes_of(cfg):
    """``m -> `` the unknowns of block m that the m-filters keep (``imaging.filter_m0``, ``filter_m1_lmin``,
    ``zero_monopole``: :func:`filter_mask` on I and on each of Q, U, V's ``l <= stokes_lmax``), the size of its
    Cholesky factor; 0 where they remove every unknown (m = 0 by default: never factorised)."""
    lmax, lmax_p, filters = cfg.mmode.lmax, stokes_lmax_of(cfg), m_filters(cfg.imaging)

    def size(m):
        n_p = stokes_sizes(m, lmax, lmax_p)[1]
        keep = filter_mask(m, lmax, **filters)
        return int(keep.sum() + 3 * keep[:n_p].sum())
    return size


def gram_dtype(cfg):
    """The Grams' precision in a block task and on disk: the accumulation's (complex64 for ``transfer.dtype:
    float32``)."""
    return complex_dtype(cfg.transfer.dtype).name


def gram_itemsize(cfg):
    """Bytes of a complex of the transfer's precision: a Gram element in a block task (:func:`gram_dtype`), a
    Fourier array's element."""
    return complex_dtype(cfg.transfer.dtype).itemsize


def kept_in_memory(cfg):
    """Whether phase two keeps a channel's Grams and factors in memory (:data:`KEPT_BYTES`): complex128 each,
    ``BLOCK_BYTES_PER_ELEMENT`` per element of ``sum_m N_m^2``."""
    size = sizes_of(cfg)
    return BLOCK_BYTES_PER_ELEMENT * sum(float(size(m)) ** 2 for m in range(cfg.mmode.lmax + 1)) <= KEPT_BYTES


#: where a channel's Grams and factors do not fit ``KEPT_BYTES``, phase two keeps the factors of the m with the
#: largest normal equations within this (complex128, 16 bytes an element: each is factorised once, the rest again
#: per observation; the factor's cost grows as N^3 and its bytes as N^2, so the largest save the most a byte).
#: At the paper's scale the 112 largest (m = 0, emptied by the m-filters, is never factorised), 57 % of a
#: factorisation of every m, in a phase-two task planned at 5.9 GB (2 GiB: 48, a third, 4.8 GB; the stage
#: 3.84 -> 3.50 h at 171 SGEMM GFLOP/s, 2.24 -> 2.04 h at 293, `mmflow plan`)
FACTORS_KEPT_BYTES = 4 * 2 ** 30


def factors_kept(cfg):
    """The m whose factors phase two keeps when not all are kept (:data:`FACTORS_KEPT_BYTES`): the largest
    factors (:func:`factor_sizes_of`; none for an m the filters empty) first, while their complex128 bytes fit."""
    size = factor_sizes_of(cfg)
    kept, used = [], 0.0
    for m in sorted((m for m in range(cfg.mmode.lmax + 1) if size(m)), key=lambda m: (-size(m), m)):
        b = np.dtype(np.complex128).itemsize * float(size(m)) ** 2
        if used + b > FACTORS_KEPT_BYTES:
            break
        kept.append(m)
        used += b
    return sorted(kept)
