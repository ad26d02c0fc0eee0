"""Model coherencies of compact sources: direction + primary beam + 3-D baseline fringe.

``M_ij(t) = sum_p S_p A(r_p(t)) exp(2 pi i (x_j - x_i) . r_p(t) / lambda)`` over the points
``p`` of a source (one for a point source, a sampled grid per Gaussian component), evaluated
by :func:`mmflow.simulate.visibilities.simulate_drift_scan` (the same measurement equation the
simulator uses, so calibration models and simulated data agree to rounding).
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import radec_to_vec
from mmflow.simulate.scene import source_points_date
from mmflow.simulate.visibilities import SkyPoints, simulate_drift_scan
from mmflow.sky.frames import rotation_matrix, source_enu
from mmflow.sky.sources import epoch_year


def source_coherencies(telescope, freq_hz, lsts, sources, epoch_jd, pairs=None, dtype=np.complex128, out=None):
    """Model visibilities of each source separately.

    Parameters
    ----------
    telescope : mmflow.telescope.Telescope
    freq_hz : float
    lsts : array (n_time,) sidereal angles (rad)
    sources : list of :class:`mmflow.sky.sources.Source` or :class:`SkyPoints` (frame of date)
    epoch_jd : float
    pairs : ndarray (n_bl, 2), optional
    dtype : working precision of :func:`~mmflow.simulate.visibilities.simulate_drift_scan`
    out : ndarray (n_src, n_time, n_bl) complex, optional
        Filled in place, one source at a time (no stacked copy: at 256 antennas eleven sources of
        a time chunk are 1.5 GB in complex128).

    Returns
    -------
    ndarray (n_src, n_time, n_bl) complex128 (or ``out``'s dtype), Jy (published flux through the beam)
    """
    pairs = telescope.antenna_pairs() if pairs is None else np.asarray(pairs)
    if out is None:
        out = np.empty((len(sources), len(np.atleast_1d(lsts)), len(pairs)), np.complex128)
    for s, src in enumerate(sources):
        pts = src if isinstance(src, SkyPoints) else source_points_date(src, freq_hz, epoch_jd)
        simulate_drift_scan(telescope, freq_hz, lsts, pts, pairs=pairs, dtype=dtype, out=out[s])
    return out


def source_vector_date(source, epoch_jd):
    """Frame-of-date unit vector of a catalogue source's catalogued position."""
    v = radec_to_vec(np.deg2rad(source.ra_deg), np.deg2rad(source.dec_deg))
    return rotation_matrix("icrs", "date", epoch_jd) @ v


def apparent_flux(telescope, freq_hz, lsts, sources, epoch_jd):
    """Published flux x beam at each source's position: (n_src, n_time) Jy, and elevation (rad)."""
    flux, elev = [], []
    for src in sources:
        enu = source_enu(telescope, lsts, source_vector_date(src, epoch_jd))
        flux.append(float(src.flux(freq_hz, epoch_year(epoch_jd))) * telescope.beam.power_enu(enu, freq_hz))
        elev.append(np.arcsin(np.clip(enu[..., 2], -1, 1)))
    return np.array(flux), np.array(elev)


def coherencies_at_offsets(telescope, freq_hz, lsts, source, epoch_jd, offsets_rad, pairs=None,
                           flux_scale=None, dtype=np.complex128):
    """One source's coherency per integration at fitted positions (n_time, n_bl).

    ``offsets_rad`` (n_time, 2): (east, north) tangent-plane offsets per integration (e.g.
    from :func:`mmflow.calibrate.source_models.fit_point_position`); ``flux_scale`` (n_time,)
    multiplies the published flux. Used for the sources that are subtracted, not peeled.
    """
    lsts = np.atleast_1d(lsts)
    scale = np.ones(len(lsts)) if flux_scale is None else np.asarray(flux_scale, float)
    return np.stack([simulate_drift_scan(telescope, freq_hz, lsts[t:t + 1],
                                         source_points_date(source, freq_hz, epoch_jd, offsets_rad[t], scale[t]),
                                         pairs=pairs, dtype=dtype)[0] for t in range(len(lsts))])
