"""Model coherencies of compact sources: direction + primary beam + 3-D baseline fringe.

``M_ij(t) = sum_p S_p A(r_p(t)) exp(2 pi i (x_j - x_i) . r_p(t) / lambda)`` over the points
``p`` of a source (one for a point source, a sampled grid per Gaussian component), evaluated
by :func:`mmflow.simulate.visibilities.simulate_drift_scan` (the same measurement equation the
simulator uses, so calibration models and simulated data agree to rounding).

Through an E-field beam (:func:`source_correlations`), the four linear correlations of each
source, unpolarised (the catalogue holds no polarisation)::

    M_ij,pq(t) = sum_p J_p(r_p) S_p J_q(r_p)^H exp(2 pi i (x_j - x_i) . r_p / lambda),   S_p = I_p 1

(pq = xx, yy, xy, yx; :func:`mmflow.simulate.polarised.simulate_polarised_drift_scan`): the parallel
hands each through its own feed's power beam ``|J_p|^2``, and the cross hands the beam's
``J_x J_y^H``, nonzero off the zenith (for short dipoles ``-I r_E r_N``).
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import radec_to_vec
from mmflow.simulate.polarised import simulate_polarised_drift_scan
from mmflow.simulate.scene import source_points_date, unpolarised
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


def source_correlations(telescope, freq_hz, lsts, sources, epoch_jd, pairs=None, dtype=np.complex128, out=None, *,
                        jones):
    """Model visibilities of each source separately in the four correlations through the E-field beam.

    Parameters as :func:`source_coherencies`'s, and ``jones`` a :class:`mmflow.telescope.jones.JonesBeam`
    (feeds x east, y north); the sources unpolarised.

    Returns
    -------
    ndarray (n_src, n_time, n_bl, 4) of ``dtype`` (or ``out``'s): xx, yy, xy, yx (Jy, ``avg``: an
    unpolarised source of flux I gives ``xx = |J_x|^2 I``)
    """
    pairs = telescope.antenna_pairs() if pairs is None else np.asarray(pairs)
    lsts = np.atleast_1d(lsts)
    if out is None:
        out = np.empty((len(sources), len(lsts), len(pairs), 4), dtype)
    for s, src in enumerate(sources):
        pts = src if isinstance(src, SkyPoints) else source_points_date(src, freq_hz, epoch_jd)
        vis = simulate_polarised_drift_scan(telescope, jones, freq_hz, lsts, unpolarised(pts), pairs)
        out[s] = np.moveaxis(vis, 1, -1)  # (time, corr, bl) -> (time, bl, corr)
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
