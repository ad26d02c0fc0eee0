"""Flux densities of compact sources in maps (paper section 3.6, the flux-scale figure).

``S = [sum_disc I - n_disc median_annulus(I)] / [sum_disc P - n_disc median_annulus(P)]``

with ``I`` the map and ``P`` the PSF of a 1 Jy source at the same position (both Jy/sr, any
common unit): the disc sum measures the source, the annulus median removes the local
background, and the PSF's disc sum (measured the same way) converts to Jy whatever the PSF's
shape and its filtered, zero-mean sidelobes.
"""
from __future__ import annotations

import healpy
import numpy as np

from mmflow.imaging.psf import psf_alm
from mmflow.sky.frames import rotate_alm
from mmflow.sky.harmonics import synthesize_at


def disc_minus_annulus(hmap, vec, radius_rad, annulus_rad, nside=None):
    """``sum_disc map - n_disc median(map over the annulus r_in < d < r_out)``.

    ``hmap``: a HEALPix (RING) map, or a function ``pixels -> values`` of a map of ``nside``
    (e.g. :func:`alm_sampler`: only the disc's and annulus's pixels are ever evaluated).
    """
    if callable(hmap):
        values = hmap
    else:
        nside = healpy.npix2nside(len(hmap))
        values = hmap.__getitem__
    disc = healpy.query_disc(nside, vec, radius_rad)
    outer = healpy.query_disc(nside, vec, annulus_rad[1])
    inner = healpy.query_disc(nside, vec, annulus_rad[0])
    ring = np.setdiff1d(outer, inner, assume_unique=True)
    return float(np.sum(values(disc)) - len(disc) * np.median(values(ring)))


def alm_sampler(alm, lmax, nside, map_to_alm=None, scale=1.0):
    """``pixels -> scale x f(r_p)``: the pixels of an ``nside`` map of the sky ``alm``, evaluated
    where asked (:func:`mmflow.sky.harmonics.synthesize_at`) instead of synthesising the sphere.

    ``map_to_alm`` (3x3) takes the map's frame to the alm's (None: the same frame); ``scale``
    converts the alm's unit to the map's. Equals ``alm2map`` of the rotated alm at those pixels.
    """
    def values(pix):
        vecs = np.array(healpy.pix2vec(nside, np.asarray(pix))).T
        return scale * synthesize_at(alm, vecs if map_to_alm is None else vecs @ np.asarray(map_to_alm).T, lmax)

    return values


def source_flux(hmap, psf_map, vec, radius_rad, annulus_rad):
    """Flux density (Jy) of the source at ``vec`` given the map (or sampler) of a 1 Jy PSF there."""
    nside = healpy.npix2nside(len(hmap))
    return disc_minus_annulus(hmap, vec, radius_rad, annulus_rad) / \
        disc_minus_annulus(psf_map, vec, radius_rad, annulus_rad, nside)


def flux_scale_rows(hmap, sources, psf_map_at, freq_hz, radius_rad, annulus_rad, rotation=None, epoch_year=None):
    """One row per catalogue source: name, measured and model flux (Jy), their ratio.

    ``sources``: :class:`mmflow.sky.sources.Source` objects; ``psf_map_at(vec)`` returns the
    map of a 1 Jy PSF at ``vec`` (same pixels and frame as ``hmap``); ``rotation`` takes ICRS
    vectors to the map's frame (None: the map is ICRS).
    """
    rows = []
    for src in sources:
        v = src.vector_icrs() if rotation is None else rotation @ src.vector_icrs()
        rows.append(flux_row(src, source_flux(hmap, psf_map_at(v), v, radius_rad, annulus_rad), freq_hz, epoch_year))
    return rows


def flux_deviations(hmap, noise, vecs, radii_rad, annuli_rad, psf_disc_sums):
    """What one noise realisation does to :func:`source_flux` of each source (Jy).

    ``dS_s = [D(I + n, r_s) - D(I, r_s)] / D(P_s, r_s)`` with ``D`` :func:`disc_minus_annulus`,
    ``I`` the map, ``n`` a noise-only map of the same imaging (a map or a sampler, e.g. of the
    jackknife ``(odd - even) / 2``, whose variance is the full map's) and ``D(P_s)`` the PSF's
    at the source. Adding the noise to the map itself, not measuring it alone, keeps what the
    annulus median does with sky structure: where the annulus holds a gradient or sidelobes,
    the median moves with the noise of the few pixels near its rank (about one pixel's noise),
    far more than on a noise-only annulus (its noise / sqrt(n)). The rms of ``dS`` over
    realisations is the flux error.
    """
    nside = healpy.npix2nside(len(hmap))
    sample = noise if callable(noise) else noise.__getitem__

    def noisy(pix):
        return hmap[pix] + sample(pix)

    return np.array([(disc_minus_annulus(noisy, v, r, a, nside) - disc_minus_annulus(hmap, v, r, a)) / p
                     for v, r, a, p in zip(vecs, radii_rad, annuli_rad, psf_disc_sums)])


def flux_row(src, measured_jy, freq_hz, epoch_year=None, **extra):
    """The flux-scale row of one source: name, measured and model flux (Jy), their ratio, reference."""
    model = float(src.flux(freq_hz, epoch_year))
    return {"name": src.name, "freq_hz": float(freq_hz), "measured_jy": float(measured_jy), "model_jy": model,
            "ratio": float(measured_jy) / model, "reference": src.spectrum.reference, **extra}


def peel_flux_factors(mode, scale, dd_gains, peel_code=1, subtract_code=2):
    """Per integration, the factor by which the data held a peeled or subtracted source's model.

    Peeling removes ``h_i conj(h_j) M_ij`` with ``M`` the model (published flux x beam) and
    ``h`` the direction-dependent gains; subtracting removes ``a M_ij``. The factor is ``a``
    for a subtracted integration and, for a peeled one, the mean over baselines ``i < j`` of
    ``|h_i| |h_j|``,

    ``f = [(sum_i |h_i|)^2 - sum_i |h_i|^2] / [N (N - 1)]``,

    (amplitudes: the gains' phases follow the ionosphere, not the flux); NaN where the source
    was skipped. ``measured flux = f x published flux`` at each integration.

    Parameters
    ----------
    mode : int array (time,), 0 skip, ``peel_code``, ``subtract_code``
    scale : float array (time,), the fitted scale of subtracted integrations
    dd_gains : complex array (time, antenna), the DD gains of peeled integrations
    """
    amp = np.abs(np.asarray(dd_gains))
    n = amp.shape[-1]
    peeled = (amp.sum(-1) ** 2 - (amp**2).sum(-1)) / max(n * (n - 1), 1)
    mode = np.asarray(mode)
    return np.where(mode == peel_code, peeled, np.where(mode == subtract_code, np.asarray(scale, float), np.nan))


def psf_map_function(ops, lmax, nside, map_to_date=None, scale=1.0):
    """``psf_map_at(vec)``: the HEALPix map of a 1 Jy source at ``vec`` seen through the imaging.

    ``vec`` is in the map's frame; ``map_to_date`` (3x3, None: the map is in the frame of
    date) takes it to the frame of date, where the PSF
    ``a_PSF = (G + eps I)^-1 G conj(Y_lm(r0))`` (:func:`mmflow.imaging.psf.psf_alm`, with the
    data's filters) is computed, and the PSF's alm are rotated back with ``map_to_date^T``.
    ``scale`` converts Jy/sr to the map's unit (e.g. K per Jy/sr at the channel's frequency),
    though :func:`source_flux` is a ratio and needs it only when the maps' units differ.
    """
    def psf_map_at(vec):
        v = np.asarray(vec, float)
        v_date = v if map_to_date is None else map_to_date @ v
        alm = psf_alm(ops, lmax, v_date)
        if map_to_date is not None:
            alm = rotate_alm(alm, np.asarray(map_to_date).T, lmax)
        return scale * healpy.alm2map(alm, nside, lmax=lmax)

    return psf_map_at
