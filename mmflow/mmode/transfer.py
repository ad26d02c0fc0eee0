"""Transfer matrices ``B_m`` through ring FFTs and one real GEMM per m (north/south folded).

For baseline b (sky frame at ``phi = 0``, in wavelengths) the baseline transfer function is
``f_b(r) = A(r) exp(2 pi i b . r)``, and

``B_lm(b) = int f_b Y_lm dOmega = sum_k w_k lambda_lm(theta_k) F_{k,m}(b)``,
``F_{k,m}(b) = sum_j f_b(theta_k, phi_j) exp(+i m phi_j)``

on a Gauss-Legendre grid (``w_k`` includes ``2 pi / n_phi``). The quadrature is exact when
``f_b`` is band-limited to ``L_f`` and the grid is exact to ``lmax + L_f``. The -m row of
b is the +m row of -b: ``F_{k,m}(-b) = conj(F_{k,-m}(b))``, so one FFT gives both rows.
Folding rings ``k`` and ``pi - theta_k`` with ``lambda_lm(pi-theta) = (-1)^{l+m} lambda_lm(theta)``
halves the GEMM: even ``l+m`` use ``F_k + F_k'``, odd use ``F_k - F_k'``.

Kernels here are plain numpy/ducc0 on in-memory arrays; dask maps them over chunks.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import ducc0
import numpy as np

from mmflow.conventions import enu_to_equatorial_matrix, unit_vectors
from mmflow.mmode.legendre import legendre_table
from mmflow.threads import n_threads


def fringe_bandlimit(b_wavelengths, beam_lmax):
    """Band limit of ``A exp(2 pi i b.r)``: ``2 pi |b| + 3 (2 pi |b|)^(1/3) + beam + 8``.

    Beyond ``l ~ 2 pi |b|`` the fringe's harmonic content falls like a Bessel function
    past its turning point; the cube-root term covers the transition region.
    """
    kb = 2 * np.pi * float(np.max(b_wavelengths, initial=0.0))
    return int(np.ceil(kb + 3 * kb ** (1 / 3) + beam_lmax + 8))


@dataclass
class TransferGrid:
    """A Gauss-Legendre grid in the sky frame at ``phi = 0`` with the beam sampled on it.

    Attributes
    ----------
    lmax : int
        Largest l of the transfer coefficients computed on this grid.
    quad_lmax : int
        Band limit the quadrature is exact to (``lmax + L_f``).
    theta, weights : ndarray (n_theta,)
    n_phi : int
    beam : ndarray (n_theta, n_phi) float64, zero below the horizon
    active : ndarray of int
        North-ring indices k whose ring or mirror ring sees the beam.
    """

    lmax: int
    quad_lmax: int
    theta: np.ndarray
    weights: np.ndarray
    n_phi: int
    vectors: np.ndarray
    beam: np.ndarray
    active: np.ndarray
    _tables: dict = field(default_factory=dict, repr=False)

    @property
    def n_theta(self):
        return len(self.theta)

    def tables(self, m, dtype):
        """Weighted Legendre tables ``(w_k lambda_lm(theta_k))`` split by parity of ``l - m``."""
        key = (m, np.dtype(dtype).str)
        if key not in self._tables:
            north = self.active
            t = legendre_table(m, self.lmax, self.theta[north]) * self.weights[north]
            self._tables[key] = (np.ascontiguousarray(t[0::2], dtype), np.ascontiguousarray(t[1::2], dtype))
        return self._tables[key]


def make_grid(lat_rad, beam, freq_hz, lmax, fringe_lmax):
    """Build the quadrature grid exact to ``lmax + fringe_lmax`` and sample the beam on it."""
    quad = lmax + fringe_lmax
    n_theta = quad // 2 + 2
    n_theta += n_theta % 2  # even: rings pair up north/south
    n_phi = ducc0.fft.good_size(quad + 2)
    theta = ducc0.misc.GL_thetas(n_theta)
    weights = ducc0.misc.GL_weights(n_theta, n_phi)
    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    vec = unit_vectors(theta[:, None], phi[None, :])
    enu = vec @ enu_to_equatorial_matrix(lat_rad)  # r_enu = M^T r_eq
    a = beam.power_enu(enu, freq_hz)
    half = n_theta // 2
    seen = (a[:half].max(axis=1) > 0) | (a[::-1][:half].max(axis=1) > 0)
    return TransferGrid(lmax, quad, theta, weights, n_phi, vec, a, np.flatnonzero(seen))


def _ring_fourier(grid, b, rings, cdtype):
    """``F_{k,m}`` for ``m = -n_phi/2..`` on ``rings`` for baselines ``b`` (n_b, 3), in wavelengths.

    Returns complex array ``(n_b, len(rings), n_phi)`` (FFT order in the last axis).
    """
    rdtype = np.float32 if cdtype == np.complex64 else np.float64
    vec = grid.vectors[rings]  # (nr, nphi, 3)
    a = grid.beam[rings]
    out = np.zeros((len(b), len(rings), grid.n_phi), cdtype)
    up = a > 0
    vu = vec[up]  # (n_up, 3)
    au = a[up].astype(rdtype)
    for i, bi in enumerate(b):
        ph = vu @ (2 * np.pi * bi)
        ph -= 2 * np.pi * np.round(ph / (2 * np.pi))  # reduce in float64, then evaluate
        ph = ph.astype(rdtype, copy=False)
        vals = np.empty(len(ph), cdtype)
        vals.real = np.cos(ph) * au
        vals.imag = np.sin(ph) * au
        out[i][up] = vals
    ducc0.fft.c2c(out, axes=(2,), forward=False, inorm=0, out=out, nthreads=n_threads())
    return out


def iter_transfer_blocks(grid, b_wavelengths, lmax_b=None, mmax=None, dtype=np.float64, ring_block=64):
    """Yield ``(m, B_m)`` for ``m = 0..mmax`` for a chunk of baselines.

    Parameters
    ----------
    grid : TransferGrid
    b_wavelengths : ndarray (n_b, 3)
        Baselines in the sky frame at ``phi = 0``, in wavelengths.
    lmax_b : ndarray (n_b,), optional
        Per-baseline lmax; coefficients with ``l > lmax_b`` are set to zero.
    dtype : float32 or float64
        Precision of the GEMM and of the blocks (complex64 / complex128 out).

    Yields
    ------
    m : int
    B_m : ndarray, shape ``(n_b, L)`` for m = 0 and ``(2 n_b, L)`` for m > 0, ``L = lmax - m + 1``;
        columns are ``l = m..lmax``; rows ``n_b..2n_b-1`` are the -m rows (see conventions).
    """
    b = np.asarray(b_wavelengths, float).reshape(-1, 3)
    nb = len(b)
    lmax = grid.lmax
    mmax = lmax if mmax is None else min(mmax, lmax)
    lmax_b = np.full(nb, lmax) if lmax_b is None else np.minimum(np.asarray(lmax_b), lmax)
    rdtype = np.dtype(dtype)
    cdtype = np.complex64 if rdtype == np.float32 else np.complex128
    half = grid.n_theta // 2
    north = grid.active
    nn = len(north)
    # P[m, k, c]: columns c < nb are +m of b, c >= nb are +m of -b (i.e. the -m rows)
    plus = np.zeros((mmax + 1, nn, 2 * nb), cdtype)
    minus = np.zeros((mmax + 1, nn, 2 * nb), cdtype)  # same for the mirrored (south) rings
    for start in range(0, nn, ring_block):
        ks = north[start:start + ring_block]
        for target, rings in ((plus, ks), (minus, grid.n_theta - 1 - ks)):
            f = _ring_fourier(grid, b, rings, cdtype)  # (nb, nr, nphi)
            sl = slice(start, start + len(ks))
            target[:, sl, :nb] = f[:, :, :mmax + 1].transpose(2, 1, 0)
            neg = np.conj(f[:, :, (-np.arange(mmax + 1)) % grid.n_phi])  # conj(F_{-m})
            target[:, sl, nb:] = neg.transpose(2, 1, 0)
    del half
    ell_all = np.arange(lmax + 1)
    for m in range(mmax + 1):
        even, odd = grid.tables(m, rdtype)
        s = (plus[m] + minus[m]).view(rdtype)  # (nn, 4 nb) real view
        d = (plus[m] - minus[m]).view(rdtype)
        out = np.empty((lmax - m + 1, 2 * nb), cdtype)
        out[0::2] = (even @ s).view(cdtype)
        out[1::2] = (odd @ d).view(cdtype)
        block = out.T if m > 0 else out[:, :nb].T
        mask = ell_all[m:][None, :] > np.concatenate([lmax_b, lmax_b] if m > 0 else [lmax_b])[:, None]
        block = np.where(mask, 0, block)
        yield m, block


def transfer_blocks(grid, b_wavelengths, lmax_b=None, mmax=None, dtype=np.float64):
    """All blocks of :func:`iter_transfer_blocks` in a list indexed by m."""
    return [blk for _, blk in iter_transfer_blocks(grid, b_wavelengths, lmax_b, mmax, dtype)]


def baselines_in_wavelengths(telescope, pairs, freq_hz):
    """Baseline vectors of ``pairs`` in the sky frame at ``phi = 0``, in wavelengths."""
    b_enu = telescope.baselines_enu(pairs)
    return b_enu @ enu_to_equatorial_matrix(telescope.lat_rad).T * freq_hz / 299792458.0
