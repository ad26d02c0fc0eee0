"""The part of the sky a drift-scanning array ever sees, as a HEALPix mask.

A direction at declination ``dec`` (frame of date) culminates at elevation
``90 - |lat - dec|`` degrees. A drift scan sees it at some time of the sidereal day if and
only if that highest elevation is above the beam's horizon ``h_min`` (0 for every mmflow
beam, which are zero below the horizon):

``|lat - dec| < 90 - h_min``,  i.e.  ``lat - (90 - h_min) < dec < lat + (90 - h_min)``.

For a northern site with ``h_min = 0`` the never-seen sky is the cap ``dec < lat - 90``
around the south celestial pole. The m-mode solution there is unconstrained (only the
regulariser sets it), so maps show it as masked rather than as smooth zeros.
"""
from __future__ import annotations

import healpy
import numpy as np


def observed_declination_range(lat_deg, min_elevation_deg=0.0):
    """``(dec_min, dec_max)`` in degrees of the directions that rise above ``min_elevation_deg``.

    Parameters
    ----------
    lat_deg : float
        Geodetic latitude of the array, degrees north.
    min_elevation_deg : float
        Elevation of the beam's horizon (0: the geometric horizon).
    """
    if not -90.0 <= lat_deg <= 90.0:
        raise ValueError(f"latitude {lat_deg} outside [-90, 90]")
    half = 90.0 - float(min_elevation_deg)
    return max(-90.0, lat_deg - half), min(90.0, lat_deg + half)


def observed_sky_mask(nside, lat_deg, map_to_date=None, min_elevation_deg=0.0):
    """Boolean HEALPix map (RING order), True where the array ever sees the sky.

    Parameters
    ----------
    nside : int
        HEALPix resolution of the output map.
    lat_deg : float
        Latitude of the array (degrees north).
    map_to_date : ndarray (3, 3), optional
        Rotation ``v_date = R @ v_map`` from the map's frame (ICRS, Galactic, ...) to the
        frame of date (:func:`mmflow.sky.frames.rotation_matrix`); None when the map is
        already in the frame of date.
    min_elevation_deg : float
        Elevation of the beam's horizon.

    Returns
    -------
    mask : ndarray of bool, shape (12 nside^2,)
        ``lat - (90 - h_min) < dec_date < lat + (90 - h_min)``.
    """
    vec = np.array(healpy.pix2vec(nside, np.arange(12 * nside * nside)))
    if map_to_date is not None:
        vec = np.asarray(map_to_date, float) @ vec
    dec = np.rad2deg(np.arcsin(np.clip(vec[2], -1.0, 1.0)))
    lo, hi = observed_declination_range(lat_deg, min_elevation_deg)
    return (dec > lo) & (dec < hi)
