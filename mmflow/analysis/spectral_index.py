"""Local spectral index from temperature-temperature (T-T) plots (paper section 5).

In a region where one power law holds, ``T2 = s T1 + c`` with ``s = (nu2 / nu1)^beta`` and an
unknown zero-level difference ``c``. Around each output direction ``r0`` a weighted linear
regression over the pixels ``p`` of a disc of radius ``R`` gives

``s = cov_w(T1, T2) / var_w(T1)``,  ``beta = ln s / ln(nu2 / nu1)``,
``R^2 = cov_w(T1, T2)^2 / (var_w(T1) var_w(T2))``,

with the smooth weight ``w = (1 - (d / R)^2)^2`` (d the angular distance to ``r0``) and
weighted (co)variances about the weighted means. Offsets of either map cancel exactly.
Where ``beta`` varies inside a disc the slope is biased by about
``mean(T1) cov_w(T1, s) / var_w(T1)``: structure in ``T1`` that correlates with the index
gradient (about 0.015 in ``beta`` for a gradient of 0.1 per radian in the tests).
"""
from __future__ import annotations

import healpy
import numpy as np

#: output pixels whose discs are gathered into one array (~400 input pixels each at the defaults)
DISCS_PER_BLOCK = 2048


def local_tt(map1, map2, nu1, nu2, radius_deg=10.0, nside_out=None, mask=None, min_pixels=20):
    """Spectral index and R^2 of local T-T regressions of ``map2`` on ``map1``.

    Parameters
    ----------
    map1, map2 : ndarray, HEALPix (RING) brightness temperatures at ``nu1`` and ``nu2``
    radius_deg : float, disc radius (the paper's regions are ~10-20 deg across)
    nside_out : int, resolution of the output maps (default: the input's)
    mask : bool ndarray over the input pixels to use (default: finite in both maps)
    min_pixels : discs with fewer usable pixels give NaN

    Returns
    -------
    dict of HEALPix maps at ``nside_out``: ``beta``, ``r2``, ``slope``.
    """
    t1, t2 = np.asarray(map1, float), np.asarray(map2, float)
    nside = healpy.npix2nside(len(t1))
    nside_out = nside_out or nside
    use = np.isfinite(t1) & np.isfinite(t2) if mask is None else np.asarray(mask, bool) & np.isfinite(t1 + t2)
    radius = np.deg2rad(radius_deg)
    npix_out = healpy.nside2npix(nside_out)
    out = {k: np.full(npix_out, np.nan) for k in ("beta", "r2", "slope")}
    centres = np.array(healpy.pix2vec(nside_out, np.arange(npix_out))).T
    vectors = np.array(healpy.pix2vec(nside, np.arange(len(t1)))).T
    for start in range(0, npix_out, DISCS_PER_BLOCK):  # the discs of a block as one (disc, pixel) list
        p = np.arange(start, min(start + DISCS_PER_BLOCK, npix_out))
        discs = [healpy.query_disc(nside, centres[q], radius) for q in p]
        rows = np.repeat(np.arange(len(p)), [len(d) for d in discs])
        cols = np.concatenate(discs)
        keep = use[cols]
        rows, cols = rows[keep], cols[keep]
        n = len(p)
        d2 = (np.arccos(np.clip(np.einsum("ij,ij->i", vectors[cols], centres[p][rows]), -1, 1)) / radius) ** 2
        w = (1 - np.minimum(d2, 1)) ** 2
        wsum = np.bincount(rows, w, minlength=n)
        w = w / np.where(wsum > 0, wsum, 1)[rows]
        a, b = t1[cols], t2[cols]
        da = a - np.bincount(rows, w * a, minlength=n)[rows]  # about each disc's weighted means
        db = b - np.bincount(rows, w * b, minlength=n)[rows]
        var1 = np.bincount(rows, w * da * da, minlength=n)
        var2 = np.bincount(rows, w * db * db, minlength=n)
        cov = np.bincount(rows, w * da * db, minlength=n)
        ok = (np.bincount(rows, minlength=n) >= min_pixels) & (var1 > 0) & (var2 > 0)
        s = cov[ok] / var1[ok]
        out["slope"][p[ok]] = s
        out["r2"][p[ok]] = cov[ok] ** 2 / (var1[ok] * var2[ok])
        with np.errstate(invalid="ignore", divide="ignore"):
            out["beta"][p[ok]] = np.where(s > 0, np.log(s) / np.log(nu2 / nu1), np.nan)
    return out


def three_colour(maps, freqs_hz, index=2.5, floor_percentile=1.0):
    """RGB (n_pix, 3) in [0, 1] from three maps scaled by ``nu^index``, logarithmic stretch.

    As the paper's three-colour figure: maps scaled by ``nu^2.5`` so that a spectral index of
    -2.5 is white; each channel is ``log`` of the scaled map between a common floor (the
    ``floor_percentile`` of all three) and the common maximum.
    """
    scaled = np.stack([np.asarray(m, float) * f**index for m, f in zip(maps, freqs_hz)], axis=1)
    lo = np.nanpercentile(scaled[scaled > 0], floor_percentile)
    hi = np.nanmax(scaled)
    x = np.log(np.clip(scaled, lo, hi) / lo) / np.log(hi / lo)
    return np.nan_to_num(x)
