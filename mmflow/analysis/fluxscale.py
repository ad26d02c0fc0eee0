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


def disc_minus_annulus(hmap, vec, radius_rad, annulus_rad):
    """``sum_disc map - n_disc median(map over the annulus r_in < d < r_out)``."""
    nside = healpy.npix2nside(len(hmap))
    disc = healpy.query_disc(nside, vec, radius_rad)
    outer = healpy.query_disc(nside, vec, annulus_rad[1])
    inner = healpy.query_disc(nside, vec, annulus_rad[0])
    ring = np.setdiff1d(outer, inner, assume_unique=True)
    return float(np.sum(hmap[disc]) - len(disc) * np.median(hmap[ring]))


def source_flux(hmap, psf_map, vec, radius_rad, annulus_rad):
    """Flux density (Jy) of the source at ``vec`` given the map of a 1 Jy PSF there."""
    return disc_minus_annulus(hmap, vec, radius_rad, annulus_rad) / \
        disc_minus_annulus(psf_map, vec, radius_rad, annulus_rad)


def flux_scale_rows(hmap, sources, psf_map_at, freq_hz, radius_rad, annulus_rad, rotation=None, epoch_year=None):
    """One row per catalogue source: name, measured and model flux (Jy), their ratio.

    ``sources``: :class:`mmflow.sky.sources.Source` objects; ``psf_map_at(vec)`` returns the
    map of a 1 Jy PSF at ``vec`` (same pixels and frame as ``hmap``); ``rotation`` takes ICRS
    vectors to the map's frame (None: the map is ICRS).
    """
    rows = []
    for src in sources:
        v = src.vector_icrs() if rotation is None else rotation @ src.vector_icrs()
        measured = source_flux(hmap, psf_map_at(v), v, radius_rad, annulus_rad)
        model = float(src.flux(freq_hz, epoch_year))
        rows.append({"name": src.name, "freq_hz": float(freq_hz), "measured_jy": measured, "model_jy": model,
                     "ratio": measured / model, "reference": src.spectrum.reference})
    return rows
