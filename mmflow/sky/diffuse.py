"""Diffuse skies as a_lm: HEALPix maps in, a synthetic Galaxy-like sky for tests and the demo.

All a_lm here use healpy's layout (m-major, ``mmax = lmax``) and orthonormal ``Y_lm``.
"""
from __future__ import annotations

import healpy
import numpy as np

from mmflow.conventions import m_slice, unit_vectors
from mmflow.sky.frames import rotate_alm, rotation_matrix
from mmflow.sky.harmonics import point_sources_alm


def map_to_alm(hpx_map, lmax, iterations=3):
    """HEALPix map -> a_lm with Jacobi iterations (healpy ``map2alm``)."""
    return healpy.map2alm(np.asarray(hpx_map, float), lmax=lmax, iter=iterations, use_pixel_weights=False)


def alm_to_map(alm, nside, lmax):
    """a_lm -> HEALPix map (RING ordering)."""
    return healpy.alm2map(np.asarray(alm, np.complex128), nside, lmax=lmax)


def synthetic_sky_kelvin(freq_hz, lmax, epoch_jd, nside=None, seed=0, t150=300.0, beta=-2.5,
                         plane_ratio=4.0, plane_width_deg=6.0, power_index=-2.4):
    """A synthetic diffuse sky in the frame of date, band-limited to ``lmax``.

    The brightness is a positive isotropic background plus a Galactic-plane band and
    power-law fluctuations, ``T(nu) = T_150 (nu / 150 MHz)^beta``:

    ``T = T0 [1 + plane_ratio exp(-b^2 / 2 w^2)] (1 + 0.3 g)``, where ``g`` is a unit-variance
    Gaussian random field with ``C_l ~ l^power_index``; ``b`` is Galactic latitude.

    Returns
    -------
    alm : ndarray (complex, healpy layout, kelvin)
    """
    nside = nside or max(16, 1 << int(np.ceil(np.log2(max(lmax, 8) / 1.5))))
    ell = np.arange(lmax + 1, dtype=float)
    cl = np.where(ell >= 2, np.maximum(ell, 1.0) ** power_index, 0.0)
    np.random.seed(seed)  # healpy.synalm uses numpy's global generator
    g_alm = healpy.synalm(cl, lmax=lmax)
    g = healpy.alm2map(g_alm, nside, lmax=lmax)
    g /= g.std() or 1.0
    theta, phi = healpy.pix2ang(nside, np.arange(healpy.nside2npix(nside)))
    gal_vec = unit_vectors(theta, phi)  # the map is built in Galactic coordinates
    b = np.arcsin(np.clip(gal_vec[:, 2], -1, 1))
    t0 = t150 * (freq_hz / 150e6) ** beta
    temp = t0 * (1 + plane_ratio * np.exp(-0.5 * (np.rad2deg(b) / plane_width_deg) ** 2)) * (1 + 0.3 * g)
    temp = np.maximum(temp, 0.05 * t0)
    alm_gal = map_to_alm(temp, lmax)
    return rotate_alm(alm_gal, rotation_matrix("galactic", "date", epoch_jd), lmax)


def band_limited_random_alm(lmax, seed=0, power_index=-2.0, lmin=0):
    """Random real-sky a_lm with ``C_l ~ (l+1)^power_index`` for ``lmin <= l <= lmax`` (tests)."""
    rng = np.random.default_rng(seed)
    alm = np.zeros((lmax + 1) * (lmax + 2) // 2, np.complex128)
    for m in range(lmax + 1):
        ls = np.arange(m, lmax + 1)
        sig = np.where(ls >= lmin, (ls + 1.0) ** (power_index / 2), 0.0)
        re, im = rng.normal(size=(2, len(ls)))
        alm[m_slice(lmax, m)] = sig * (re + (1j * im if m > 0 else 0)) / (np.sqrt(2) if m > 0 else 1)
    return alm


def point_source_alm(vec, flux, lmax):
    """a_lm of ``flux * delta(r - vec)``: ``a_lm = flux * conj(Y_lm(vec))``.

    Stable at any lmax (:func:`mmflow.sky.harmonics.point_sources_alm`, ducc0's normalised
    Legendre recursion; scipy's ``sph_harm_y`` is NaN from l ~ 646 on).
    """
    return point_sources_alm(np.reshape(np.asarray(vec, float), (1, 3)), np.array([flux], float), lmax)
