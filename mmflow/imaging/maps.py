"""From a_lm in the frame of date to HEALPix maps in ICRS or Galactic, in K or Jy/sr."""
from __future__ import annotations

import numpy as np

from mmflow.imaging.polarised import stokes_maps
from mmflow.sky import units
from mmflow.sky.diffuse import alm_to_map
from mmflow.sky.frames import rotate_alm, rotation_matrix


def default_nside(lmax):
    """Smallest power-of-two nside with ``3 nside > lmax`` (pixels resolve the band limit)."""
    nside = 1
    while 3 * nside <= lmax:
        nside *= 2
    return nside


def alm_to_output_map(alm_jy_sr, lmax, freq_hz, epoch_jd, frame="icrs", unit="K", nside=None):
    """Rotate from the frame of date to ``frame`` and synthesise a map in ``unit``."""
    m = alm_to_map(alm_in_frame(alm_jy_sr, lmax, epoch_jd, frame), nside or default_nside(lmax), lmax)
    return units.convert(m, "Jy/sr", unit, freq_hz)


def alm_in_frame(alm, lmax, epoch_jd, frame):
    """alm of date (healpy layout, any leading axes: e.g. T, E, B, V) rotated to ``frame`` (as they are for
    ``frame == "date"``)."""
    if frame == "date":
        return alm
    rot = rotation_matrix("date", frame, epoch_jd)
    return rotate_alm(alm, rot, lmax) if np.ndim(alm) == 1 else np.stack([rotate_alm(a, rot, lmax) for a in alm])


def stokes_alm_to_output_maps(alm_tebv, lmax, freq_hz, epoch_jd, frame="icrs", unit="K", nside=None):
    """IAU ``(I, Q, U, V)`` maps in ``frame`` and ``unit`` from ``(T, E, B, V)`` alm of date ``(4, n_alm)``.

    T, E, B and V transform alike under a rotation of the frame (E and B are defined on each
    frame's own north/east basis), so each is rotated as a scalar alm and the maps are
    synthesised in ``frame``: Q and U are then referred to that frame's north (IAU: angle from
    north through east; :func:`mmflow.imaging.polarised.stokes_maps`).
    """
    maps = stokes_maps(alm_in_frame(alm_tebv, lmax, epoch_jd, frame), nside or default_nside(lmax), lmax)
    return units.convert(maps, "Jy/sr", unit, freq_hz)
