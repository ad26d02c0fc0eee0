"""Jackknife noise of a map from even and odd integrations (paper section 4, Table 1).

Split the sidereal grid ``phi_n = 2 pi n / N`` into its even (``n = 2k``) and odd
(``n = 2k + 1``) bins. Each half is an ``N/2``-bin grid; the odd half sits half a bin of the
new grid away from ``2 pi k / (N/2)``, so its m-modes carry the phase
``exp(-i m 2 pi / N)``: they are transformed at their true angles
(``phi = 2 pi (2k + p) / N + offset``, :func:`half_mmodes`), never as if they sat on the
half grid. With the true angles every half measures the same sky m-modes (for
``m < N/2 - mmax_sky``), and ``V_m(all) = (V_m(even) + V_m(odd)) / 2`` exactly.

Imaging each half with the same operator (same Gram, eps and filters) as the full data keeps
``map_all = (map_even + map_odd) / 2``, and the jackknife estimate of the full map's noise
variance is

``sigma^2 = (1/2) mean_observed(|odd - all|^2 + |even - all|^2)``,

unbiased for independent noise in the two halves: ``odd - all = (odd - even) / 2``.
"""
from __future__ import annotations

import numpy as np

from mmflow.errors import InputError
from mmflow.mmode.transform import mmode_transform
from mmflow.sky import units


def half_mmodes(binned, mmax, parity, offset=None):
    """m-modes of the even (``parity = 0``) or odd (1) bins of an N-bin sidereal grid.

    Parameters
    ----------
    binned : ndarray (N, ...)
        Sidereally binned data on ``phi_n = 2 pi n / N (+ offset_n)``.
    offset : ndarray (N,), optional
        Per-bin offsets from :func:`mmflow.mmode.transform.sidereal_bins`.

    Returns
    -------
    ndarray (mmax + 1, 2, ...), as :func:`mmflow.mmode.transform.mmode_transform`.
    """
    n = binned.shape[0]
    if n % 2 or n // 2 < 2 * mmax + 1:
        raise InputError("jackknife", "n_bins", f"{n} sidereal bins cannot be halved for mmax={mmax}",
                         f"use an even number of bins >= {2 * (2 * mmax + 1)}")
    off = np.zeros(n) if offset is None else np.asarray(offset, float)
    shift = 2 * np.pi * parity / n + off[parity::2]
    return mmode_transform(binned[parity::2], mmax, offset=shift)


def split_mmodes(binned, mmax, offset=None):
    """``{"all", "even", "odd"}`` m-modes of one sidereal grid (the data-split axis)."""
    return {"all": mmode_transform(binned, mmax, offset=offset),
            "even": half_mmodes(binned, mmax, 0, offset), "odd": half_mmodes(binned, mmax, 1, offset)}


def jackknife_variance(map_all, map_even, map_odd, mask=None):
    """``(1/2) mean(|odd - all|^2 + |even - all|^2)`` over the pixels in ``mask``."""
    sel = slice(None) if mask is None else np.asarray(mask, bool)
    d_odd = np.asarray(map_odd)[sel] - np.asarray(map_all)[sel]
    d_even = np.asarray(map_even)[sel] - np.asarray(map_all)[sel]
    return float(0.5 * np.mean(np.abs(d_odd) ** 2 + np.abs(d_even) ** 2))


def noise_summary(sigma_jy_sr, freq_hz, beam_solid_angle_sr):
    """The noise in the units of Table 1: K and mJy/beam (``sigma Omega_beam``)."""
    return {"jy_per_sr": float(sigma_jy_sr),
            "kelvin": float(units.jy_per_sr_to_kelvin(sigma_jy_sr, freq_hz)),
            "mjy_per_beam": float(1e3 * sigma_jy_sr * beam_solid_angle_sr)}


def jackknife_noise(map_all, map_even, map_odd, mask, freq_hz, psf_table, beam_dec_deg=45.0):
    """Table 1's noise: jackknife sigma (Jy/sr, K, mJy/beam), the beam being the fitted PSF
    main lobe at ``beam_dec_deg`` (``Omega = pi / (4 ln 2) major minor``)."""
    from mmflow.imaging.psf import gaussian_solid_angle, interp_table

    sigma = np.sqrt(jackknife_variance(map_all, map_even, map_odd, mask))
    dec = np.deg2rad(beam_dec_deg)
    omega = gaussian_solid_angle(interp_table(psf_table, dec, "major"), interp_table(psf_table, dec, "minor"))
    return {**noise_summary(sigma, freq_hz, omega), "beam_solid_angle_sr": float(omega)}
