"""Seeded, switchable instrumental, ionospheric and terrestrial corruptions of model visibilities.

Every generator takes a ``numpy.random.Generator`` and returns the *truth* it injects, so
tests can compare what calibration recovers with what was put in. The data model
(visibilities ``(time, bl, pol)``, antenna ``pairs`` (n_bl, 2), autos where ``i == j``)::

    V_ij(t) = g_i(t) conj(g_j(t)) [ V^sky_ij(t)
                                    + sum_s h_si(t) conj(h_sj(t)) M^s_ij(t)      (DD sources)
                                    + c_i conj(c_j)                              (cross-talk)
                                    + a(t) e_i conj(e_j) ]                       (near-field RFI)
              + n_ij(t)

* ``g``: per-antenna, per-pol gains: a smooth bandpass, a slow drift, and the analog
  temperature sawtooth (paper section 3.2): 0.1 dB peak to peak in power with a period
  wandering between 15 and 17 min (HVAC cycles), common in shape to all antennas with a
  +-20 % per-antenna amplitude scatter.
* ``h``: direction-dependent gains of the bright sources: a refractive offset ``dr`` (a phase
  gradient ``h_i = exp(-2 pi i x_i . dr / lambda)``, which moves the source to ``r + dr``) of up
  to ~20' at 36.5 MHz scaling as ``nu^-2`` and varying on ~10 min, times ``sqrt(f(t))`` with
  ``f`` a scintillation flux factor (up to ~50 % integration-to-integration at 36.5 MHz).
* ``c``: a constant common-mode / cross-talk pattern (rank 1, does not move with the sky).
* ``e``: a near-field RFI source on the horizon (default 10 km west): spherical wavefront
  ``e_i = (d0 / d_i) exp(2 pi i d_i / lambda)``, ``d_i = |x_i - p|``, fluctuating amplitude ``a(t)``.
* flags (bad antennas, bad integrations) as zero weights, and thermal noise from the
  radiometer equation (:func:`mmflow.simulate.visibilities.thermal_noise`).

A polarised sky (full-Stokes simulations) carries the four correlations ``V_ij`` as 2 x 2 feed
matrices ``[[xx, xy], [yx, yy]]``, ``g`` one gain per feed (``G_i = diag(g_ix, g_iy)``), the feeds'
polarisation leakage ``D_i = [[1, d_ix], [-d_iy, 1]]`` (:func:`leakage_terms`), and::

    V_ij = G_i ( D_i [ V^sky_ij + sum_s h_si conj(h_sj) M^s_ij ] D_j^H + (terrestrial + receiver) 1 ) G_j^H + n_ij

with the terrestrial signals unpolarised (on xx and yy; cross-talk arises behind the feeds), the
receiver power (``system_jy``) on each feed's autocorrelation alike, and
radiometer noise on every correlation (:func:`mmflow.simulate.polarised.correlation_noise`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from astropy import units as u
from astropy.time import Time

from mmflow.conventions import SIDEREAL_DAY_S
from mmflow.import_thread import import_in_thread
from mmflow.simulate.polarised import apply_leakage, correlation_noise
from mmflow.simulate.visibilities import SkyPoints, thermal_noise
from mmflow.sky.frames import apparent_sidereal_time, source_enu, tangent_basis
from mmflow.conventions import SPEED_OF_LIGHT

ARCMIN = np.pi / 180 / 60
#: the feeds ``(p, q)`` of the correlations xx, yy, xy, yx (:func:`baseline_ends`)
FOUR_FEEDS = ((0, 1, 0, 1), (0, 1, 1, 0))


def baseline_ends(values, pairs, feeds=None):
    """``(x[..., i, p], x[..., j, q])``: a per-antenna, per-feed quantity at both ends of every baseline.

    Parameters
    ----------
    values : ndarray (..., n_ant, n_feed)
    pairs : ndarray (n_bl, 2), the antennas ``(i, j)`` of each baseline
    feeds : pair of sequences, optional
        ``(p, q)``: polarisation k correlates feed ``p[k]`` of antenna i with feed ``q[k]`` of
        antenna j (xx, yy, xy, yx: ``((0, 1, 0, 1), (0, 1, 1, 0))``). Default: ``p = q`` = the last axis.

    Returns
    -------
    two ndarrays (..., n_bl, n_pol)
    """
    pairs = np.asarray(pairs)
    values = np.asarray(values)
    n_feed = values.shape[-1]
    p, q = (np.arange(n_feed),) * 2 if feeds is None else (np.asarray(feeds[0]), np.asarray(feeds[1]))
    flat = values.reshape(values.shape[:-2] + (-1,))  # (..., n_ant * n_feed): one gather per end, not two
    return (np.take(flat, pairs[:, :1] * n_feed + p, axis=-1),
            np.take(flat, pairs[:, 1:] * n_feed + q, axis=-1))


def gain_products(gains, pairs, feeds=None):
    """``g_ip conj(g_jq)`` for every baseline (and polarisation, :func:`baseline_ends`' ``feeds``).

    Parameters
    ----------
    gains : ndarray (..., n_ant, n_feed)
    pairs : ndarray (n_bl, 2)
    feeds : see :func:`baseline_ends` (default: one gain per polarisation, ``p = q``)

    Returns
    -------
    ndarray (..., n_bl, n_pol)
    """
    gi, gj = baseline_ends(gains, pairs, feeds)
    gj = np.conjugate(gj, out=gj) if np.iscomplexobj(gj) else gj  # the gathers are new arrays: in place
    return np.multiply(gj, gi, out=gj if gj.dtype == np.result_type(gi, gj) else None)


def sawtooth_db(times_s, rng, amplitude_db=0.1, period_s=(900.0, 1020.0), wander_s=3 * 3600.0):
    """The HVAC gain sawtooth in dB (power), zero mean, ``amplitude_db`` peak to peak.

    The instantaneous period wanders sinusoidally between ``period_s`` (default 15-17 min)
    with a ``wander_s`` cycle; the cycle phase is the integral of ``1 / P(t)``.
    """
    t = np.asarray(times_s, float)
    p0, p1 = period_s
    ph0 = rng.uniform(0, 2 * np.pi)
    tt = np.linspace(t.min(), t.max(), max(2, 20 * len(t)))
    period = 0.5 * (p0 + p1) + 0.5 * (p1 - p0) * np.sin(2 * np.pi * tt / wander_s + ph0)
    cyc = np.concatenate([[0.0], np.cumsum(np.diff(tt) / period[1:])]) + rng.uniform()
    frac = np.interp(t, tt, cyc) % 1.0
    return amplitude_db * (frac - 0.5)


def antenna_gains(n_ant, n_pol, times_s, rng, *, bandpass=True, drift=True, sawtooth=True,
                  amplitude_db=0.1, period_s=(900.0, 1020.0), drift_rad=0.3, drift_period_s=12 * 3600.0):
    """Per-antenna, per-pol complex gains (time, n_ant, n_pol) of one channel.

    bandpass: a random complex gain per antenna and pol (amplitude 1 +- 0.2, any phase);
    drift: a slow phase drift of ``drift_rad`` amplitude with period ``drift_period_s``;
    sawtooth: :func:`sawtooth_db` multiplying the power by ``10^(dB/10)`` (the voltage gain
    by ``10^(dB/20)``) with a per-antenna amplitude scatter of 20 %.

    Returns (gains, sawtooth_power_factor (time, n_ant, n_pol)).
    """
    t = np.asarray(times_s, float)
    g = np.ones((len(t), n_ant, n_pol), np.complex128)
    if bandpass:
        g *= (1 + 0.2 * rng.uniform(-1, 1, (n_ant, n_pol))) * np.exp(2j * np.pi * rng.uniform(size=(n_ant, n_pol)))
    if drift:
        ph = rng.uniform(0, 2 * np.pi, (n_ant, n_pol))
        g *= np.exp(1j * drift_rad * np.sin(2 * np.pi * t[:, None, None] / drift_period_s + ph))
    power = np.ones(g.shape)
    if sawtooth:
        db = sawtooth_db(t, rng, amplitude_db, period_s)
        scatter = 1 + 0.2 * rng.uniform(-1, 1, (n_ant, n_pol))
        power = 10 ** (db[:, None, None] * scatter / 10)
        g *= np.sqrt(power)
    return g, power


def ionospheric_offsets(n_src, times_s, freq_hz, rng, max_arcmin=20.0, ref_freq_hz=36.5e6,
                        timescale_s=600.0, n_waves=6):
    """Refractive offsets (n_src, n_time, 2) in radians (east, north on the sky).

    A sum of ``n_waves`` travelling-wave sinusoids per source and axis with periods around
    ``timescale_s``, scaled so that the largest |offset| is ``max_arcmin (ref/nu)^2``.
    """
    t = np.asarray(times_s, float)
    per = timescale_s * rng.uniform(0.5, 2.0, (n_src, 2, n_waves))
    ph = rng.uniform(0, 2 * np.pi, (n_src, 2, n_waves))
    amp = rng.uniform(0.5, 1.0, (n_src, 2, n_waves))
    off = np.einsum("saw,sawt->sta", amp, np.sin(2 * np.pi * t[None, None, None, :] / per[..., None] + ph[..., None]))
    peak = np.max(np.linalg.norm(off, axis=-1), axis=1, keepdims=True)[..., None]
    return off / np.maximum(peak, 1e-300) * max_arcmin * ARCMIN * (ref_freq_hz / freq_hz) ** 2


def scintillation(n_src, n_time, freq_hz, rng, sigma_ref=0.2, ref_freq_hz=36.5e6):
    """Flux factors (n_src, n_time): ``exp(sigma z - sigma^2/2)``, ``sigma = sigma_ref (ref/nu)^2``.

    Independent from integration to integration: with ``sigma_ref = 0.2`` adjacent integrations
    at 36.5 MHz differ by more than 50 % about 8 % of the time ("not unusual", paper 3.4).
    """
    s = sigma_ref * (ref_freq_hz / freq_hz) ** 2
    return np.exp(s * rng.normal(size=(n_src, n_time)) - s**2 / 2)


def direction_dependent_gains(telescope, freq_hz, lsts, src_vec_date, offsets, flux_factor=None):
    """``h_si(t) = sqrt(f_s(t)) exp(-2 pi i x_i . dr_s(t) / lambda)``: (n_src, n_time, n_ant).

    ``dr`` is the tangent-plane offset (east, north, radians) of source ``s`` expressed as a
    3-D vector in ENU at each time, so ``h_i conj(h_j) M_ij`` moves the source by ``dr``.
    """
    src_vec_date = np.atleast_2d(src_vec_date)
    e, n = tangent_basis(src_vec_date)  # (n_src, 3) frame of date
    dr_date = offsets[..., 0:1] * e[:, None] + offsets[..., 1:2] * n[:, None]  # (src, time, 3)
    rots = source_enu(telescope, lsts, np.eye(3))  # (3, n_time, 3): row k = ENU of date axis k
    dr_enu = np.einsum("stk,ktl->stl", dr_date, rots)
    lam = SPEED_OF_LIGHT / freq_hz
    h = np.exp(-2j * np.pi * np.einsum("stl,al->sta", dr_enu, telescope.layout.enu) / lam)
    if flux_factor is not None:
        h *= np.sqrt(flux_factor)[..., None]
    return h


def dd_visibilities(coherencies, dd_gains, pairs):
    """``sum_s h_si conj(h_sj) M^s_ij``: (n_time, n_bl[, n_corr]) from (n_src, n_time, n_bl[, n_corr]) and
    (n_src, n_time, n_ant) (one scalar gain per antenna and source: the ionosphere acts on both feeds alike)."""
    prod = gain_products(dd_gains[..., None], pairs)[..., 0]
    return np.einsum("stb,stb...->tb...", prod, coherencies)


def crosstalk_pattern(n_ant, rng, amplitude_jy=5.0):
    """A constant rank-1 cross-talk pattern vector ``c`` (n_ant,): ``V_ij = c_i conj(c_j)``."""
    return np.sqrt(amplitude_jy) * (1 + 0.3 * rng.normal(size=n_ant)) * np.exp(2j * np.pi * rng.uniform(size=n_ant))


def near_field_rfi(enu, freq_hz, n_time, rng, distance_m=10e3, azimuth_deg=270.0, amplitude_jy=5.0,
                   fluctuation=0.5, correlation=5):
    """A near-field emitter on the horizon: pattern ``e`` (n_ant,) and amplitude ``a(t)`` (n_time,).

    ``e_i = (d0 / d_i) exp(2 pi i d_i / lambda)`` (spherical wavefront, ``d0`` the distance to the
    array centre); ``a(t) = amplitude_jy * |1 + fluctuation * smoothed noise|`` with a
    correlation length of ``correlation`` integrations (arcing power lines flicker).
    """
    az = np.deg2rad(azimuth_deg)
    p = distance_m * np.array([np.sin(az), np.cos(az), 0.0])
    d = np.linalg.norm(np.asarray(enu) - p, axis=1)
    e = distance_m / d * np.exp(2j * np.pi * d * freq_hz / SPEED_OF_LIGHT)
    z = rng.normal(size=n_time + 4 * correlation)
    k = np.exp(-0.5 * (np.arange(-2 * correlation, 2 * correlation + 1) / max(correlation, 1e-9)) ** 2)
    z = np.convolve(z, k / np.sqrt((k**2).sum()), mode="valid")[:n_time]
    return e, amplitude_jy * np.abs(1 + fluctuation * z)


def sun_points(jd, freq_hz, flux_jy=2e4, ref_freq_hz=74e6, alpha=1.8, radius_arcmin=20.0, n_ring=8):
    """The quiet Sun as a uniform disc (``SkyPoints`` in the frame of date at ``jd``).

    Flux ``flux_jy (nu / ref)^alpha`` with a positive index (thermal corona); radius 20'
    (the corona is larger than the optical disc at these frequencies); the disc is sampled on
    ``n_ring`` rings of points with equal area. The position is the apparent Sun at ``jd``
    (astropy, offline); it moves ~1 deg/day, so call once per chunk of integrations.
    """
    c = _sun_vector_date(float(jd))
    e, n = tangent_basis(c)
    rad = radius_arcmin * ARCMIN
    pts, w = [], []
    for k in range(1, n_ring + 1):  # ring k stands for the k-th of n_ring equal-area annuli
        r = rad * np.sqrt((k - 0.5) / n_ring)
        m = 6 * k
        a = 2 * np.pi * (np.arange(m) + 0.5 * (k % 2)) / m
        pts.extend(c + r * (np.cos(a)[:, None] * n + np.sin(a)[:, None] * e))
        w.extend([1.0 / (n_ring * m)] * m)
    pts = np.array(pts)
    pts /= np.linalg.norm(pts, axis=1)[:, None]
    w = np.array(w)
    return SkyPoints(pts, w * flux_jy * (freq_hz / ref_freq_hz) ** alpha)


def _sun_vector_date(jd):
    # deferred: astropy.coordinates takes 0.1-0.2 s to import (docs/performance.md)
    from astropy.coordinates import TETE, get_sun

    t = Time(jd, format="jd", scale="utc")
    s = get_sun(t).transform_to(TETE(obstime=t))
    v = s.cartesian.xyz.value
    return v / np.linalg.norm(v)


def rank1_visibilities(vec, amplitude, pairs):
    """``a(t) v_i conj(v_j)``: (n_time, n_bl)."""
    pairs = np.asarray(pairs)
    return np.asarray(amplitude)[:, None] * (vec[pairs[:, 0]] * np.conj(vec[pairs[:, 1]]))[None]


def flag_weights(n_time, pairs, n_pol, rng, n_bad_antennas=0, bad_integration_fraction=0.0):
    """Weights (time, bl, pol) of 1 with bad antennas and bad integrations set to 0.

    Returns (weights, bad_antennas, bad_integrations).
    """
    pairs = np.asarray(pairs)
    n_ant = int(pairs.max()) + 1
    bad_ant = np.sort(rng.choice(n_ant, n_bad_antennas, replace=False)) if n_bad_antennas else np.zeros(0, int)
    bad_t = np.flatnonzero(rng.uniform(size=n_time) < bad_integration_fraction)
    w = np.ones((n_time, len(pairs), n_pol))
    w[:, np.isin(pairs[:, 0], bad_ant) | np.isin(pairs[:, 1], bad_ant)] = 0.0
    w[bad_t] = 0.0
    return w, bad_ant, bad_t


@dataclass
class Corruption:
    """What :func:`corrupt` injected (the truth calibration should recover)."""

    gains: np.ndarray = None            # (time, ant, pol)
    sawtooth_power: np.ndarray = None   # (time, ant, pol)
    terrestrial: list = field(default_factory=list)  # [(pattern (ant,), amplitude (time,))]
    noise_sigma: np.ndarray = None      # (time, bl, pol); None for the four correlations
    weights: np.ndarray = None          # (time, bl, pol)


def corrupt(vis, pairs, rng, *, times_s=None, gains=None, terrestrial=(), noise=None, weights=None,
            four_correlations=False, dterms=None, receiver_jy=0.0):
    """Apply gains, add terrestrial components and noise to (time, bl, pol) visibilities.

    Parameters
    ----------
    vis : ndarray (time, bl, pol): the sky (including any DD-corrupted sources, from
        :func:`dd_visibilities`), in Jy: the parallel hands (one feed per column), or with
        ``four_correlations`` xx, yy, xy, yx (:data:`mmflow.simulate.polarised.CORRELATIONS`).
    gains : ndarray (time, ant, pol) or None
        Applied as ``g_ip conj(g_jq) (V + terrestrial)`` (from :func:`antenna_gains`; with
        ``four_correlations`` one gain per feed x, y: ``feeds`` :data:`FOUR_FEEDS`).
    terrestrial : sequence of (pattern (ant,), amplitude (time,)) rank-1 components, added before
        the gains (they enter the receivers like sky signals), unpolarised: on the parallel hands.
    noise : dict(bandwidth_hz, integration_s) or None
        Radiometer noise from the corrupted autocorrelations (pairs with ``i == j`` needed); with
        ``four_correlations`` on every correlation (:func:`mmflow.simulate.polarised.correlation_noise`).
    weights : ndarray (time, bl, pol) or None, e.g. from :func:`flag_weights`; flagged samples
        are set to 0 in the output.
    dterms : ndarray complex (ant, 2) or None
        With ``four_correlations``: the feeds' polarisation leakage ``V -> D_i V D_j^H``
        (:func:`mmflow.simulate.polarised.apply_leakage`), applied to the sky before the
        terrestrial signals (cross-talk arises behind the feeds) and the gains: the Jones chain
        ``G_i D_i``.
    receiver_jy : float
        With ``four_correlations``: a receiver power added to each feed's autocorrelation (xx, yy) after
        the leakage (it arises behind the feeds), before the gains.

    Returns
    -------
    (corrupted (time, bl, pol) complex128, Corruption)
    """
    pairs = np.asarray(pairs)
    out = np.array(vis, np.complex128, copy=True)
    truth = Corruption(gains=gains, terrestrial=list(terrestrial), weights=weights)
    if dterms is not None:
        if not four_correlations:
            raise ValueError("polarisation leakage mixes the four correlations: give xx, yy, xy, yx")
        out = np.moveaxis(apply_leakage(np.moveaxis(out, -1, -2), pairs, dterms), -2, -1)
    parallel = slice(0, 2) if four_correlations else slice(None)  # xx, yy lead CORRELATIONS
    if receiver_jy and four_correlations:
        out[:, pairs[:, 0] == pairs[:, 1], parallel] += receiver_jy
    for vec, amp in terrestrial:
        out[..., parallel] += rank1_visibilities(vec, amp, pairs)[..., None]
    if gains is not None:
        out *= gain_products(gains, pairs, FOUR_FEEDS if four_correlations else None)
    if noise is not None and four_correlations:
        correlation_noise(out, pairs, noise["bandwidth_hz"], noise["integration_s"], rng)
    elif noise is not None:
        auto_idx = np.full(int(pairs.max()) + 1, -1)
        autos = pairs[:, 0] == pairs[:, 1]
        auto_idx[pairs[autos, 0]] = np.flatnonzero(autos)
        ai, aj = auto_idx[pairs[:, 0]], auto_idx[pairs[:, 1]]
        if np.any(ai < 0) or np.any(aj < 0):
            raise ValueError("thermal noise needs every antenna's autocorrelation in pairs")
        n, sigma = thermal_noise(out, out[:, ai].real, out[:, aj].real, noise["bandwidth_hz"],
                                 noise["integration_s"], rng, autos.reshape((1, -1) + (1,) * (out.ndim - 2)))
        out += n
        truth.noise_sigma = sigma
    if weights is not None:
        out[np.broadcast_to(weights, out.shape) == 0] = 0.0
    return out, truth


def utc_at_lsts(lsts, layout, near_jd, iterations=3):
    """UTC Julian dates near ``near_jd`` at which the site's apparent LST
    (:func:`mmflow.sky.frames.apparent_sidereal_time`, pyuvdata's ``lst_array``) equals ``lsts``
    (rad, one sidereal day of consecutive integrations).

    The simulation is a function of LST alone (:func:`mmflow.conventions.drift_scan_lsts`); files
    written through pyuvdata carry times, from which a reader recomputes the LST. Solves
    ``LST(t) = phi`` by Newton steps with ``dLST/dt = 2 pi / 86164.0905 s``: the first
    integration's time is found first, the rest follow from the unwrapped LSTs.
    """
    phi = np.unwrap(np.asarray(lsts, float))
    rate = 2 * np.pi / (SIDEREAL_DAY_S / 86400.0)  # rad per (UTC) day
    t = np.full(phi.shape, float(near_jd)) + (phi - phi[0]) / rate
    for _ in range(iterations):
        err = np.angle(np.exp(1j * (phi - apparent_sidereal_time(t, layout.lon_deg))))
        t = t + err / rate
    return t


def to_uvdata(vis, weights, pairs, telescope, times_jd, freq_hz, pols=("xx", "yy"), channel_width_hz=None,
              integration_s=None, x_orientation=None, pol_convention=None):
    """A pyuvdata ``UVData`` of (time, bl, pol) or (time, bl, freq, pol) visibilities, to write as UVH5 or MS.

    ``freq_hz``: one frequency, or one per channel of a (time, bl, freq, pol) ``vis``.
    ``pol_convention``: pyuvdata's statement of how the parallel hands relate to Stokes I
    (``"avg"``: XX = I, mmflow's simulator; ``"sum"``: XX = I / 2), written into the file.

    ``ant_1 = i``, ``ant_2 = j`` for ``pairs[b] = (i, j)`` and the data as they are: pyuvdata's
    ``uvw = x_2 - x_1`` and mmflow's ``V_ij ~ exp(+2 pi i (x_j - x_i).r / lambda)`` agree (ingest
    with ``conjugate: false``). Weights of 0 become flags. Antenna positions are the layout's
    ENU positions about its centre. Autocorrelations of the parallel hands are written as their real
    part, as a correlator writes them (the simulator's radiometer noise is complex on every baseline;
    an antenna's XY and YX are complex).
    ``x_orientation="east"`` labels linear polarisations as pyuvdata does for such feeds:
    ``pols=("ee", "nn")`` are then XX and YY (the same polarisation numbers, -5 and -6).
    """
    import_in_thread("pyuvdata")  # its first import would pin this frame and its locals (mmflow.import_thread)
    # deferred: astropy.coordinates (0.1-0.2 s) and pyuvdata (2-3.5 s) to import (docs/performance.md)
    from astropy.coordinates import EarthLocation
    from pyuvdata import Telescope as UVTelescope
    from pyuvdata import UVData
    from pyuvdata.utils import ECEF_from_ENU

    lay = telescope.layout
    loc = EarthLocation.from_geodetic(lay.lon_deg * u.deg, lay.lat_deg * u.deg, lay.height_m * u.m)
    centre = np.array([loc.x.to_value("m"), loc.y.to_value("m"), loc.z.to_value("m")])
    ecef = ECEF_from_ENU(lay.enu, center_loc=loc) - centre
    n_ant = lay.n_ant
    tel = UVTelescope.new("mmflow-sim", loc, antenna_positions=ecef, antenna_names=list(lay.names),
                          antenna_numbers=list(range(n_ant)), instrument="mmflow-corrupt", mount_type="fixed",
                          feeds=["x", "y"] if len(pols) > 1 else ["x"], x_orientation=x_orientation)
    vis = np.array(vis, np.complex128)
    freqs = np.atleast_1d(np.asarray(freq_hz, float))
    if vis.ndim == 3:
        vis, weights = vis[:, :, None], np.asarray(weights)[..., None, :]
    T, B, F, P = vis.shape
    autos = np.asarray(pairs)[:, 0] == np.asarray(pairs)[:, 1]
    parallel = [k for k, p in enumerate(pols) if str(p)[0] == str(p)[-1]]  # xx, yy (ee, nn): real autos
    sub = vis[:, autos]
    sub[..., parallel] = sub[..., parallel].real
    vis[:, autos] = sub
    data = vis.reshape(T * B, F, P)
    flags = (np.broadcast_to(weights, vis.shape) == 0).reshape(T * B, F, P)
    uv = UVData.new(freq_array=freqs, polarization_array=list(pols), times=np.asarray(times_jd),
                    x_orientation=x_orientation,
                    telescope=tel, antpairs=[tuple(map(int, p)) for p in pairs], do_blt_outer=True, data_array=data,
                    flag_array=flags, integration_time=integration_s or telescope.integration_s,
                    channel_width=channel_width_hz or telescope.channel_width_hz, vis_units="Jy",
                    time_axis_faster_than_bls=False)
    if pol_convention is not None:
        uv.pol_convention = pol_convention
    return uv


@dataclass
class DayCorruptions:
    """The whole drift scan's corruptions of one channel (the truth), sliced per time chunk.

    gains (time, ant, pol) or None; dd_offsets (n_dd, time, 2) rad and dd_flux (n_dd, time)
    for the sources with direction-dependent gains; terrestrial [(pattern (ant,), amplitude (time,))];
    dterms (ant, 2) complex or None: the feeds' polarisation leakage (full-Stokes simulations).
    """

    gains: np.ndarray
    dd_offsets: np.ndarray
    dd_flux: np.ndarray
    terrestrial: list
    dterms: np.ndarray = None


def leakage_terms(n_ant, rng, amplitude):
    """D-terms ``d_x, d_y`` of every antenna: ``|d|`` uniform in ``[amplitude / 5, amplitude]``, phases
    uniform (a dipole array's few-percent leakage: mechanical misalignment and feed coupling); (n_ant, 2)."""
    mag = rng.uniform(amplitude / 5, amplitude, (n_ant, 2))
    return mag * np.exp(2j * np.pi * rng.uniform(size=(n_ant, 2)))


def day_corruptions(n_ant, freq_hz, times_s, n_dd, enu, rng, *, gains=True, sawtooth_db=0.1,
                    ionosphere_arcmin=20.0, scintillation_sigma=0.2, crosstalk_jy=0.0, rfi_jy=0.0, n_pol=2,
                    leakage=0.0):
    """Draw every corruption of one channel for the whole scan (``times_s`` all integrations).

    Drawn once per channel so that any time chunk sees the same gains, offsets and terrestrial
    amplitudes (:func:`antenna_gains`, :func:`ionospheric_offsets`, :func:`scintillation`,
    :func:`crosstalk_pattern`, :func:`near_field_rfi`, :func:`leakage_terms`); switched-off parts
    draw nothing (the leakage last, so the others are the same draws with and without it).
    """
    t = np.asarray(times_s, float)
    g = None
    if gains or sawtooth_db > 0:
        g, _ = antenna_gains(n_ant, n_pol, t, rng, bandpass=gains, drift=gains, sawtooth=sawtooth_db > 0,
                             amplitude_db=sawtooth_db)
    offsets = ionospheric_offsets(n_dd, t, freq_hz, rng, ionosphere_arcmin) if n_dd else np.zeros((0, len(t), 2))
    flux = scintillation(n_dd, len(t), freq_hz, rng, scintillation_sigma) if n_dd else np.zeros((0, len(t)))
    terr = []
    if crosstalk_jy > 0:
        terr.append((crosstalk_pattern(n_ant, rng, crosstalk_jy), np.ones(len(t))))
    if rfi_jy > 0:
        terr.append(near_field_rfi(enu, freq_hz, len(t), rng, amplitude_jy=rfi_jy))
    d = leakage_terms(n_ant, rng, leakage) if leakage > 0 else None
    return DayCorruptions(g, offsets, flux, terr, d)


def corrupted_visibilities(telescope, freq_hz, lsts, sky_vis, dd_coherencies, dd_vecs, day, rows, pairs,
                           noise_rng=None, integration_s=None, system_jy=0.0, four_correlations=False):
    """One time chunk of corrupted ``(time, bl, pol)`` visibilities (see the module docstring).

    ``sky_vis``: the sky without the DD sources, (time, bl) the same for every feed (a scalar beam),
    (time, bl, pol) each feed's parallel hand (a Jones beam's feeds), or with ``four_correlations``
    (time, bl, 4) the correlations xx, yy, xy, yx of a polarised sky (the output then holds the
    four, with the day's D-terms); ``dd_coherencies`` (n_dd, time, bl[, pol or 4]) the DD sources'
    model visibilities alike and ``dd_vecs`` (n_dd, 3) their frame-of-date directions; ``day`` a
    :class:`DayCorruptions`, ``rows`` the chunk's integrations in it; ``system_jy`` a receiver (and
    unmodelled background) power added to the autocorrelations of each feed, uncorrelated between
    antennas and feeds (with four correlations after the D-terms: it arises behind the feeds): it
    enters the radiometer noise and the gains act on it like on the sky.
    """
    n_pol = 2 if day.gains is None else day.gains.shape[-1]
    vis = np.array(sky_vis, np.complex128)
    autos = np.asarray(pairs)[:, 0] == np.asarray(pairs)[:, 1]
    if not four_correlations:
        vis[:, autos] += system_jy
    if len(dd_vecs):
        h = direction_dependent_gains(telescope, freq_hz, lsts, dd_vecs, day.dd_offsets[:, rows],
                                      day.dd_flux[:, rows])
        vis += dd_visibilities(dd_coherencies, h, pairs)
    if vis.ndim == 2:
        vis = np.repeat(vis[..., None], n_pol, axis=-1)
    terr = [(vec, amp[rows]) for vec, amp in day.terrestrial]
    noise = None if noise_rng is None else {"bandwidth_hz": telescope.channel_width_hz, "integration_s": integration_s}
    out, _ = corrupt(vis, pairs, noise_rng, gains=None if day.gains is None else day.gains[rows],
                     terrestrial=terr, noise=noise, four_correlations=four_correlations, dterms=day.dterms,
                     receiver_jy=system_jy)
    return out
