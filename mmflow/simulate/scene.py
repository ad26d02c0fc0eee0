"""A whole simulated drift scan, as plain functions: its LSTs, its sky, one time chunk of it.

The ``simulate`` stage is a thin adapter over these; the tests and notebooks call them too.
"""
from __future__ import annotations

import numpy as np

from mmflow.mmode.transfer import fringe_bandlimit
from mmflow.simulate.corrupt import corrupted_visibilities
from mmflow.simulate.polarised import (CORRELATIONS, PolarisedPoints, correlation_noise,
                                      simulate_polarised_drift_scan)
from mmflow.simulate.visibilities import (SkyPoints, auto_columns, gauss_legendre_points, simulate_drift_scan,
                                         thermal_noise)
from mmflow.sky.frames import rotation_matrix, tangent_basis
from mmflow.sky.diffuse import synthetic_sky_kelvin
from mmflow.sky.sources import epoch_year, get_sources
from mmflow.sky.units import kelvin_to_jy_per_sr
from mmflow.telescope.jones import feed_telescopes
from mmflow.conventions import SPEED_OF_LIGHT


def sky_points(telescope, freq_hz, epoch_jd, diffuse_lmax=None, seed=0, sources=(), quad_oversample=48):
    """The simulated sky at one frequency as weighted directions in the frame of date.

    The diffuse part (:func:`mmflow.sky.diffuse.synthetic_sky_kelvin`, band-limited to
    ``diffuse_lmax``) is sampled on a Gauss-Legendre grid exact for the sky times the
    longest fringe (``diffuse_lmax + fringe band limit + quad_oversample``); catalogue
    sources (their spectra at ``freq_hz``, Cas A's secular decrease at the epoch's year) are
    rotated from ICRS to the frame of date.
    """
    pts = SkyPoints(np.zeros((0, 3)), np.zeros(0))
    if diffuse_lmax:
        pts = pts + diffuse_points(telescope, freq_hz, epoch_jd, diffuse_lmax, seed, quad_oversample)
    for src in get_sources(list(sources)):
        pts = pts + source_points_date(src, freq_hz, epoch_jd)
    return pts


def diffuse_points(telescope, freq_hz, epoch_jd, diffuse_lmax, seed=0, quad_oversample=48):
    """The synthetic diffuse sky (:func:`mmflow.sky.diffuse.synthetic_sky_kelvin`, band limit
    ``diffuse_lmax``) on its Gauss-Legendre grid (frame of date), exact for the sky times the longest
    fringe (``diffuse_lmax + fringe band limit + quad_oversample``)."""
    alm = kelvin_to_jy_per_sr(synthetic_sky_kelvin(freq_hz, diffuse_lmax, epoch_jd, seed=seed), freq_hz)
    return gauss_legendre_points(
        alm, diffuse_lmax, diffuse_quad_lmax(telescope, freq_hz, diffuse_lmax, quad_oversample)
    )


def diffuse_quad_lmax(telescope, freq_hz, diffuse_lmax, quad_oversample=48):
    """Band limit of the diffuse sky's quadrature: ``diffuse_lmax + fringe band limit + quad_oversample``,
    the fringe's of the longest baseline at ``freq_hz``."""
    b = np.linalg.norm(telescope.baselines_enu(), axis=1) * freq_hz / SPEED_OF_LIGHT
    return diffuse_lmax + fringe_bandlimit(b, telescope.beam.lmax_hint) + quad_oversample


def feed_columns(telescope, corrupted):
    """The telescopes a simulation's unpolarised sky is observed through: each feed's (its power beam)
    for a corrupted simulation with a Jones beam, else the telescope itself (one column)."""
    feeds = feed_telescopes(telescope) if corrupted else None
    return feeds or [telescope]


def diffuse_columns(telescope, corrupted, full_stokes):
    """Columns of a diffuse sky's samples (:func:`drift_samples`): the four correlations of a full-Stokes
    simulation, else one per :func:`feed_columns`."""
    return len(CORRELATIONS) if full_stokes else len(feed_columns(telescope, corrupted))


def drift_samples(telescope, freq_hz, points, lsts, corrupted, jones=None):
    """``(time, baseline, feed)`` visibilities of ``points`` at the sidereal angles ``lsts``, through
    :func:`feed_columns` (what :func:`simulate_chunk` adds as ``extra`` once interpolated), summed in
    single precision as :func:`simulate_chunk` sums its sky (rounding ~1e-5 of the largest
    visibility, against radiometer noise ~3e-3 of it at 13 s and 24 kHz). With the E-field beam
    ``jones`` (a full-Stokes simulation) the four correlations xx, yy, xy, yx of the unpolarised
    ``points`` instead (:func:`mmflow.simulate.polarised.simulate_polarised_drift_scan`, single precision:
    what :func:`simulate_polarised_chunk` adds as ``extra``)."""
    if jones is not None:
        v = simulate_polarised_drift_scan(telescope, jones, freq_hz, lsts, unpolarised(points),
                                          telescope.antenna_pairs(), dtype=np.complex64)
        return np.moveaxis(v, 1, -1)
    return np.stack([simulate_drift_scan(t, freq_hz, lsts, points, t.antenna_pairs(), np.complex64)
                     for t in feed_columns(telescope, corrupted)], axis=-1)


def source_points_date(source, freq_hz, epoch_jd, offset_rad=(0.0, 0.0), flux_scale=1.0):
    """A catalogue source as :class:`SkyPoints` in the frame of date, optionally shifted.

    ``offset_rad`` = (east, north) tangent-plane shift of every point (a refractive offset or
    a fitted position), ``flux_scale`` multiplies the published flux.
    """
    vec, flux = source.points(freq_hz, epoch_year(epoch_jd))
    vec = vec @ rotation_matrix("icrs", "date", epoch_jd).T
    if np.any(np.asarray(offset_rad) != 0):
        e, n = tangent_basis(vec)
        vec = vec + offset_rad[0] * e + offset_rad[1] * n
        vec /= np.linalg.norm(vec, axis=1)[:, None]
    return SkyPoints(vec, flux * flux_scale)


def simulate_chunk(telescope, lsts, skies, noise_rng=None, integration_s=None, corrupted=None, rows=None,
                   system_jy=0.0, extra=None):
    """Visibilities ``(time, baseline, freq, pol)`` complex64 of one time chunk, one sky per frequency.

    Uncorrupted, the one polarisation is Stokes I. With ``noise_rng``, radiometer noise
    ``sigma^2 = V_ii V_jj / (dnu tau)`` is added from the simulated autocorrelations (which
    therefore must be among the baselines).

    ``corrupted``: per frequency ``(day, dd_points, dd_vecs)`` -- a
    :class:`mmflow.simulate.corrupt.DayCorruptions`, the direction-dependent sources as
    :class:`SkyPoints` (not in ``skies``) and their directions -- gives XX and YY through
    :func:`mmflow.simulate.corrupt.corrupted_visibilities`, each through its feed's power beam when
    the beam is an E-field beam (:func:`mmflow.telescope.jones.feed_telescopes`); ``rows`` are the chunk's
    integrations in the day; ``system_jy`` the receiver power of the corrupted autocorrelations.
    ``extra``: per frequency visibilities ``(time, baseline)`` (``(time, baseline, feed)`` through each
    feed's power beam) added to the sky's before corruption and noise (the diffuse sky interpolated
    from its samples, :mod:`mmflow.simulate.drift_modes`).
    """
    pairs = telescope.antenna_pairs()
    n_pol = 1 if corrupted is None else 2
    out = np.zeros((len(lsts), len(pairs), len(telescope.freqs_hz), n_pol), np.complex64)
    if noise_rng is not None:
        is_auto, ci, cj = auto_columns(pairs)
    columns = feed_columns(telescope, corrupted is not None)  # a corrupted Jones beam: each feed its own

    def drift_scan(points, f, dtype=np.complex128):
        if len(columns) == 1:
            return simulate_drift_scan(columns[0], f, lsts, points, pairs, dtype)
        return np.stack([simulate_drift_scan(t, f, lsts, points, pairs, dtype) for t in columns], axis=-1)

    for fi, f in enumerate(telescope.freqs_hz):
        v = drift_scan(skies[fi], f, np.complex64)
        if extra is not None:
            v = (v + extra[fi]).astype(v.dtype)
        if corrupted is not None:
            day, dd_points, dd_vecs = corrupted[fi]
            dd = np.stack([drift_scan(p, f) for p in dd_points]) if dd_points else np.zeros((0,) + v.shape, complex)
            out[:, :, fi] = corrupted_visibilities(telescope, f, lsts, v, dd, dd_vecs, day, rows, pairs, noise_rng,
                                                   integration_s, system_jy)
            continue
        if noise_rng is not None:
            autos = np.real(v[:, is_auto])
            noise, _ = thermal_noise(v, autos[:, ci], autos[:, cj], telescope.channel_width_hz, integration_s,
                                     noise_rng, is_auto)
            v = v + noise
        out[:, :, fi, 0] = v
    return out


def unpolarised(points):
    """:class:`SkyPoints` as :class:`~mmflow.simulate.polarised.PolarisedPoints` with Q = U = V = 0."""
    stokes = np.zeros((len(points.flux_jy), 4))
    stokes[:, 0] = points.flux_jy
    return PolarisedPoints(points.vectors, stokes)


def polarised_sky_points(telescope, freq_hz, epoch_jd, diffuse_lmax=None, seed=0, sources=(), fractions=None,
                         quad_oversample=48):
    """The sky of :func:`sky_points` with Stokes parameters: the diffuse sky unpolarised, each catalogue
    source ``s`` with ``(Q, U, V) = I_s (q_s, u_s, v_s)`` for its fractions in ``fractions``
    (``{name: (q, u, v)}``, IAU; absent: unpolarised), every component of a resolved source alike."""
    parts = [unpolarised(sky_points(telescope, freq_hz, epoch_jd, diffuse_lmax, seed, (), quad_oversample))]
    parts += [polarised_source_points(src, freq_hz, epoch_jd, fractions) for src in get_sources(list(sources))]
    return joined(parts)


def polarised_source_points(source, freq_hz, epoch_jd, fractions=None):
    """A catalogue source's components in the frame of date with ``(I, I q, I u, I v)`` for its fractions
    ``(q, u, v)`` in ``fractions`` (``{name: (q, u, v)}``, IAU; absent: unpolarised)."""
    pts = source_points_date(source, freq_hz, epoch_jd)
    q, u, v = (fractions or {}).get(source.name, (0.0, 0.0, 0.0))
    return PolarisedPoints(pts.vectors, pts.flux_jy[:, None] * np.array([1.0, q, u, v]))


def joined(parts):
    """One :class:`~mmflow.simulate.polarised.PolarisedPoints` of several."""
    return PolarisedPoints(np.concatenate([p.vectors for p in parts]), np.concatenate([p.stokes_jy for p in parts]))


def simulate_polarised_chunk(telescope, jones, lsts, skies, noise_rng=None, integration_s=None, corrupted=None,
                             rows=None, system_jy=0.0, extra=None):
    """The four linear correlations of one time chunk: ``(parallel, cross)``, each ``(time, baseline,
    freq, 2)`` complex64, the parallel hands xx, yy and the cross hands xy, yx (x east, y north), one
    :class:`~mmflow.simulate.polarised.PolarisedPoints` sky per frequency through the E-field beam
    ``jones`` (:func:`mmflow.simulate.polarised.simulate_polarised_drift_scan`: direct sums, independent
    of the transfer code). With ``noise_rng``, radiometer noise on every correlation
    (:func:`mmflow.simulate.polarised.correlation_noise`, ``sigma_pq^2 = V_ii^pp V_jj^qq / (dnu tau)``).

    ``corrupted``, ``rows``, ``system_jy``: as :func:`simulate_chunk`'s, the direction-dependent sources
    as PolarisedPoints: gains per feed, the day's D-terms, DD gains and terrestrial signals
    (:func:`mmflow.simulate.corrupt.corrupted_visibilities` on the four correlations). ``extra``: per
    frequency ``(time, baseline, correlation)`` visibilities added to the sky's before corruption and noise
    (the diffuse sky interpolated from its samples, :func:`drift_samples`)."""
    pairs = telescope.antenna_pairs()
    out = np.zeros((len(lsts), len(pairs), len(telescope.freqs_hz), len(CORRELATIONS)), np.complex64)

    def drift_scan(points, f):  # (time, baseline, correlation)
        return np.moveaxis(simulate_polarised_drift_scan(telescope, jones, f, lsts, points, pairs), 1, -1)

    for fi, f in enumerate(telescope.freqs_hz):
        v = drift_scan(skies[fi], f)
        if extra is not None:
            v = v + extra[fi]
        if corrupted is not None:
            day, dd_points, dd_vecs = corrupted[fi]
            dd = np.stack([drift_scan(p, f) for p in dd_points]) if dd_points else np.zeros((0,) + v.shape, complex)
            v = corrupted_visibilities(telescope, f, lsts, v, dd, dd_vecs, day, rows, pairs, noise_rng,
                                       integration_s, system_jy, four_correlations=True)
        elif noise_rng is not None:
            correlation_noise(v, pairs, telescope.channel_width_hz, integration_s, noise_rng)
        out[:, :, fi] = v
    return out[..., :2], out[..., 2:]
