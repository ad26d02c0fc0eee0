"""The 8-stand array's transfer blocks and a Tikhonov imager through them, shared by the products
and day-split tests (``tests/conftest.py`` holds the ``blocks`` fixture)."""
import healpy
import numpy as np
import scipy.linalg as sla

from mmflow.conventions import m_slice, n_alm
from mmflow.imaging import psf
from mmflow.imaging.filters import filter_mask
from mmflow.mmode.engine import chunk_blocks, plan_chunks

LMAX, FREQ = 24, 40e6


def transfer_blocks(telescope):
    """Transfer blocks B_m of ``telescope`` at FREQ, LMAX (one chunk: rows follow the pair list)."""
    chunks, lmax_b = plan_chunks(telescope, FREQ, LMAX, chunk_size=10**6, per_baseline_lmax=False)
    assert len(chunks) == 1 and np.all(chunks[0].index == np.arange(len(chunks[0].index)))
    return dict(chunk_blocks(telescope, FREQ, chunks[0], LMAX, lmax_b))


def to_time(blocks, alm, n_bins):
    """Band-limited drift scan V(phi_n) = sum_m V_m exp(i m phi_n) of a sky alm, shape (N, n_bl)."""
    nb = blocks[0].shape[0]
    phi = 2 * np.pi * np.arange(n_bins) / n_bins
    v = np.zeros((n_bins, nb), complex)
    for m, b in blocks.items():
        vm = b @ alm[m_slice(LMAX, m)]
        v += np.exp(1j * m * phi)[:, None] * vm[None, :nb]
        if m > 0:
            v += np.exp(-1j * m * phi)[:, None] * np.conj(vm[None, nb:])
    return v


class Imager:
    """Tikhonov maps from m-modes through the block operators (the same for every split)."""

    def __init__(self, blocks, eps):
        self.blocks = blocks
        self.ops = {m: psf.block_operator(m, b.conj().T @ b, eps, filter_mask(m, LMAX)) for m, b in blocks.items()}

    def alm(self, mm):
        out = np.zeros(n_alm(LMAX), complex)
        nb = self.blocks[0].shape[0]
        for m, b in self.blocks.items():
            op = self.ops[m]
            if op.cho is None:
                continue
            v = mm[m, 0, :nb] if m == 0 else np.concatenate([mm[m, 0], mm[m, 1]])
            blk = np.zeros(LMAX - m + 1, complex)
            blk[op.keep] = sla.cho_solve(op.cho, (b.conj().T @ v)[op.keep])
            out[m_slice(LMAX, m)] = blk
        return out

    def map(self, mm, nside=16):
        return healpy.alm2map(self.alm(mm), nside, lmax=LMAX)
