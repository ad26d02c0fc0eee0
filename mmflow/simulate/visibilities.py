"""Drift-scan visibilities straight from the measurement equation (paper eq. 1).

``V_ij(phi) = int A(r) I(r) exp(2 pi i (x_j - x_i) . r / lambda) dOmega``

evaluated for each sidereal angle ``phi`` in the local ENU frame, with 3-D antenna
positions. The sky is a set of weighted directions in the frame of date (point sources,
HEALPix pixels, or Gauss-Legendre nodes of a band-limited a_lm sky). As in matvis, the
per-antenna factors ``z_ap = exp(2 pi i x_a . r_p / lambda) = C + i S`` are formed once per
time and all baselines come from one symmetric rank-k product: with ``P = [C; S]`` and
``Q = P W P^T`` (BLAS ``?syrk``), ``V = conj(Z) W Z^T`` has ``Re V = Q_CC + Q_SS`` and
``Im V = Q_CS - Q_CS^T``.
This module deliberately shares no code with :mod:`mmflow.mmode` so it can check it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import blas

from mmflow.conventions import enu_to_equatorial_matrix, unit_vectors
from mmflow.telescope.array import C_LIGHT


@dataclass
class SkyPoints:
    """Directions (frame of date) with flux weights in Jy: ``sum_p flux_p delta(r - r_p)``."""

    vectors: np.ndarray  # (n, 3)
    flux_jy: np.ndarray  # (n,)

    def __add__(self, other):
        return SkyPoints(np.concatenate([self.vectors, other.vectors]),
                         np.concatenate([self.flux_jy, other.flux_jy]))


def healpix_points(hpx_map_jy_sr):
    """Pixels of a HEALPix map (Jy/sr, frame of date) as weighted directions (pixel quadrature)."""
    import healpy

    npix = len(hpx_map_jy_sr)
    nside = healpy.npix2nside(npix)
    vec = np.array(healpy.pix2vec(nside, np.arange(npix))).T
    return SkyPoints(vec, np.asarray(hpx_map_jy_sr, float) * 4 * np.pi / npix)


def gauss_legendre_points(alm_jy_sr, lmax, quad_lmax):
    """A band-limited sky (a_lm, Jy/sr) sampled on a Gauss-Legendre grid exact to ``quad_lmax``.

    The quadrature ``sum_p w_p I(r_p) f(r_p)`` is exact for integrands of total band
    limit ``<= quad_lmax`` (``ntheta = quad_lmax // 2 + 1``, ``nphi = quad_lmax + 1``).
    """
    import ducc0

    ntheta = quad_lmax // 2 + 2
    nphi = quad_lmax + 2
    sky = ducc0.sht.synthesis_2d(alm=np.asarray(alm_jy_sr, np.complex128)[None], spin=0, lmax=lmax,
                                 geometry="GL", ntheta=ntheta, nphi=nphi)[0]
    theta = ducc0.misc.GL_thetas(ntheta)
    w = ducc0.misc.GL_weights(ntheta, nphi)
    phi = 2 * np.pi * np.arange(nphi) / nphi
    vec = unit_vectors(theta[:, None], phi[None, :]).reshape(-1, 3)
    return SkyPoints(vec, (sky * w[:, None]).ravel())


def simulate_drift_scan(telescope, freq_hz, lsts, sky, pairs=None, dtype=np.complex128):
    """Noise-free visibilities for every sidereal angle in ``lsts`` (radians).

    Parameters
    ----------
    telescope : mmflow.telescope.Telescope
    freq_hz : float
    lsts : array_like, shape (n_time,)
    sky : SkyPoints
    pairs : ndarray (n_bl, 2), optional
        Antenna pairs; defaults to ``telescope.antenna_pairs()``.
    dtype : complex64 or complex128
        Working precision. complex64 computes phases (in turns), sincos and the product in
        float32: ~1e-5 rad phase error for arrays of a few hundred wavelengths, ~5x faster.

    Returns
    -------
    ndarray, shape (n_time, n_bl), complex128, Jy
    """
    pairs = telescope.antenna_pairs() if pairs is None else np.asarray(pairs)
    lsts = np.atleast_1d(np.asarray(lsts, float))
    rdtype = np.float32 if np.dtype(dtype) == np.complex64 else np.float64
    x = (telescope.layout.enu / (C_LIGHT / freq_hz)).astype(rdtype)  # antenna positions, wavelengths
    n = len(x)
    out = np.empty((len(lsts), len(pairs)), np.complex128)
    syrk = blas.ssyrk if rdtype == np.float32 else blas.dsyrk
    for t, phi in enumerate(lsts):
        enu = sky.vectors @ enu_to_equatorial_matrix(telescope.lat_rad, phi)  # r_enu = M^T r_eq
        up = enu[:, 2] > 0
        r = enu[up]
        weight = (telescope.beam.power_enu(r, freq_hz) * sky.flux_jy[up]).astype(rdtype)
        phase = x @ r.T.astype(rdtype)  # (n_ant, n_up), in turns
        phase -= np.rint(phase)
        phase *= rdtype(2 * np.pi)
        # real form of V = conj(Z) W Z^T with Z = C + i S: Q = [C; S] W [C; S]^T
        p = np.empty((2 * n, len(r)), rdtype)
        np.cos(phase, out=p[:n])
        np.sin(phase, out=p[n:])
        if np.all(weight >= 0):
            q = syrk(1.0, p * np.sqrt(weight), lower=0)  # upper triangle of P W P^T
            q = np.triu(q) + np.triu(q, 1).T
        else:
            q = (p * weight) @ p.T
        cc, ss, cs = q[:n, :n], q[n:, n:], q[:n, n:]
        vis = (cc + ss) + 1j * (cs - cs.T)  # Re: CC^T + SS^T, Im: CS^T - SC^T
        out[t] = vis[pairs[:, 0], pairs[:, 1]]
    return out


def thermal_noise(vis, autos_i, autos_j, bandwidth_hz, integration_s, rng):
    """Radiometer-equation noise: ``sigma_ij = sqrt(V_ii V_jj / (dnu tau))`` per complex component.

    ``autos_i``/``autos_j`` are the autocorrelation powers (Jy) of each baseline's antennas,
    broadcast against ``vis``. Returns the noise array and ``sigma``.
    """
    sigma = np.sqrt(np.abs(autos_i * autos_j) / (bandwidth_hz * integration_s))
    noise = sigma / np.sqrt(2) * (rng.normal(size=vis.shape) + 1j * rng.normal(size=vis.shape))
    return noise, sigma
