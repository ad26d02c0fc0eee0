"""Drift-scan visibilities straight from the measurement equation (paper eq. 1).

``V_ij(phi) = int A(r) I(r) exp(2 pi i (x_j - x_i) . r / lambda) dOmega``

evaluated for each sidereal angle ``phi`` in the local ENU frame, with 3-D antenna
positions. The sky is a set of weighted directions in the frame of date (point sources,
HEALPix pixels, or Gauss-Legendre nodes of a band-limited a_lm sky). As in matvis, the
per-antenna factors ``z_ap = exp(2 pi i x_a . r_p / lambda)`` are formed once per time and
all baselines come from one matrix product ``V = conj(Z) diag(A I w) Z^T``.
This module deliberately shares no code with :mod:`mmflow.mmode` so it can check it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    dtype : complex dtype of the per-antenna factors (complex64: float32 sincos after a
        float64 reduction of the phase, ~10x faster, ~1e-7 relative error)

    Returns
    -------
    ndarray, shape (n_time, n_bl), complex128, Jy
    """
    pairs = telescope.antenna_pairs() if pairs is None else np.asarray(pairs)
    lsts = np.atleast_1d(np.asarray(lsts, float))
    x = telescope.layout.enu / (C_LIGHT / freq_hz)  # antenna positions in wavelengths
    out = np.empty((len(lsts), len(pairs)), np.complex128)
    for t, phi in enumerate(lsts):
        enu = sky.vectors @ enu_to_equatorial_matrix(telescope.lat_rad, phi)  # r_enu = M^T r_eq
        up = enu[:, 2] > 0
        r = enu[up]
        weight = telescope.beam.power_enu(r, freq_hz) * sky.flux_jy[up]
        phase = x @ r.T  # (n_ant, n_up), in turns
        phase -= np.round(phase)
        phase *= 2 * np.pi
        if np.dtype(dtype) == np.complex64:
            phase = phase.astype(np.float32)
        z = np.empty(phase.shape, dtype)
        z.real = np.cos(phase)
        z.imag = np.sin(phase)
        vis = (np.conj(z) * weight.astype(z.real.dtype)) @ z.T  # V_ij = sum conj(z_i) z_j w
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
