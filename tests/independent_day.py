"""A corrupted drift-scan day that mmflow did not make, written as UVH5 through pyuvdata (issue 39 item 4).

Everything here is its own code (no mmflow simulator, corruption or coherency function): the sources'
apparent directions from astropy's ``AltAz`` at each integration's UTC time (precession, nutation,
aberration), a direct point-source sum ``V_ij = sum_p S_p A(r_p) exp(2 pi i (x_j - x_i) . r_p / lambda)``
with ``A = sin(elevation)^1.5`` for both feeds (an unpolarised sky, pyuvdata's ``avg`` convention:
XX = YY = S A), and the corruptions:

- Cyg A and Cas A moved by a refractive offset that wanders between integrations (two sinusoids per
  axis, periods 5-20 min, up to ``20' (36.5 MHz / nu)^2``) and scaled by a log-normal scintillation
  factor (``sigma = 0.2 (36.5 MHz / nu)^2`` per 13 s, averaged over the integration:
  ``sigma sqrt(13 s / tau)``);
- Vir A and Tau A at their catalogue positions (the peel's subtracted sources);
- ``UNMODELLED``: point sources of 30-100 Jy that no stage models, >= 20 deg from the four;
- per-antenna, per-feed complex gains ``g_ip(t)``: amplitude 0.7-1.3 and any phase, times the HVAC
  sawtooth (0.1 dB in power, +-20 % per antenna, periods 15-17 min: the autocorrelations see it and
  the ripple correction removes it), and optionally (``drift``) a slow drift of the amplitude and the
  phase (sinusoids of 10-30 h periods: ``(1 + d_a sin) exp(i d_phi sin)``), which no default follows;
- autocorrelations ``|g_ip|^2 (sum_p S_p A_p + T_sys)`` and radiometer noise of ``sigma = T_sys /
  sqrt(dnu tau)`` on the cross-correlations (small: ~1 Jy).

With ``four=True`` the day holds xx, yy, xy and yx through crossed short dipoles instead (x east, y
north), derived here from the dipoles alone: a short dipole along ``d`` receives the field's component
along ``d``, so for an unpolarised source (coherency ``S/2`` times the identity on any orthonormal basis
of the sky plane) ``V^pq = S (d_p . d_q - (d_p . r)(d_q . r)) t(r)^2`` in the ``avg`` convention (XX = S at
the zenith): ``1 - r_e^2``, ``1 - r_n^2`` and ``-r_e r_n`` for xx, yy and xy = yx, with the E-field
horizon taper ``t = r_u^3`` of ``beam={type: short_dipole, horizon_taper: 3}``. Each correlation is
corrupted by its feeds' gains, ``V^pq_ij -> g_ip conj(g_jq) V^pq_ij``, so the uncalibrated XY phase turns
the sources' cross hands into polarisation, and the receiver power is in the parallel hands' autos only.

The file of the same sky without Cyg A, Cas A, Vir A, Tau A, corruption or noise (``truth``) says
``Jy`` and ``avg``; the corrupted one says ``uncalib`` and no convention (the gains set the scale).
"""
import numpy as np

from mmflow.telescope import ovro_lwa_layout
from tests.uvh5_helpers import SIDEREAL_DAY_S, _telescope

C = 299792458.0
#: (name, RA deg, Dec deg): the peeled (refracted, scintillating) and subtracted sources
PEELED = [("Cyg A", 299.868154, 40.733917), ("Cas A", 350.85, 58.815)]
SUBTRACTED = [("Vir A", 187.705929, 12.391122), ("Tau A", 83.633083, 22.0145)]
#: (RA deg, Dec deg, Jy): sources no stage models
UNMODELLED = [(70.0, 65.0, 60.0), (40.0, 40.0, 40.0), (130.0, 70.0, 80.0), (160.0, 40.0, 50.0),
              (230.0, 60.0, 100.0), (250.0, 25.0, 30.0), (320.0, 10.0, 70.0), (110.0, 20.0, 90.0)]
T_SYS = 2e5  # Jy, the receiver's (and diffuse sky's) share of the autocorrelations


def apparent_enu(ra_deg, dec_deg, times_jd, lay):
    """Unit ENU directions (src, time, 3) of ICRS (RA, Dec) at UTC ``times_jd`` from astropy (no refraction)."""
    from astropy import units as u
    from astropy.coordinates import AltAz, EarthLocation, SkyCoord
    from astropy.time import Time

    loc = EarthLocation.from_geodetic(lay.lon_deg * u.deg, lay.lat_deg * u.deg, lay.height_m * u.m)
    t = Time(times_jd, format="jd", scale="utc")
    src = SkyCoord(ra=np.atleast_1d(ra_deg)[:, None] * u.deg, dec=np.atleast_1d(dec_deg)[:, None] * u.deg)
    aa = src.transform_to(AltAz(obstime=t[None, :], location=loc))
    alt, az = aa.alt.rad, aa.az.rad
    return np.stack([np.cos(alt) * np.sin(az), np.cos(alt) * np.cos(az), np.sin(alt)], -1)


def scalar_beam(dirs):
    """XX and YY responses (each (n, time)), both ``sin(elevation)^1.5`` (0 below the horizon)."""
    a = np.clip(dirs[..., 2], 0, None) ** 1.5
    return [a, a]


def dipole_beams(dirs):
    """xx, yy, xy, yx responses (each (n, time)) of crossed short dipoles (x east, y north) to an unpolarised
    source: ``d_p . d_q - (d_p . r)(d_q . r)`` times the E-field taper squared, ``r_u^6`` (0 below the horizon)."""
    e, n, u = dirs[..., 0], dirs[..., 1], np.clip(dirs[..., 2], 0, None)
    taper = np.where(dirs[..., 2] > 0, u ** 6, 0.0)
    return [(1 - e**2) * taper, (1 - n**2) * taper, -e * n * taper, -e * n * taper]


def point_sum(x, lam, dirs, flux, pairs, beams=scalar_beam):
    """``sum_p S_p A(r_p) exp(2 pi i (x_j - x_i) . r_p / lambda)`` (time, bl, correlation), one ``A`` per
    correlation from ``beams(dirs)``: dirs (n, time, 3), flux (n, time)."""
    b = (x[pairs[:, 1]] - x[pairs[:, 0]]) / lam
    fringe = np.exp(2j * np.pi * np.einsum("bk,ptk->ptb", b, dirs))
    return np.stack([np.einsum("pt,ptb->tb", flux * a, fringe) for a in beams(dirs)], -1)


def _refract(r, t, rng, freq):
    """``r`` (time, 3) moved along its azimuth / altitude tangents by a wandering offset."""
    az = np.cross([0.0, 0.0, 1.0], r)
    az /= np.linalg.norm(az, axis=-1, keepdims=True)
    alt = np.cross(r, az)
    per = rng.uniform(300, 1200, (2, 2))
    ph = rng.uniform(0, 2 * np.pi, (2, 2))
    amp = np.deg2rad(20 / 60) * (36.5e6 / freq) ** 2 / 2
    off = amp * np.sin(2 * np.pi * t[:, None, None] / per + ph).sum(-1)  # (time, 2)
    moved = r + off[:, :1] * az + off[:, 1:] * alt
    return moved / np.linalg.norm(moved, axis=-1, keepdims=True)


def independent_day(radius_m=20.0, freq_hz=40e6, n_times=192, start_jd=2457802.0, seed=7, unmodelled=UNMODELLED,
                    drift=(0.0, 0.0), noise=True, four=False, truth_noise=False):
    """One sidereal day of ``n_times`` integrations, XX and YY (with ``four``: xx, yy, xy, yx through crossed
    dipoles) (dict): ``corrupted`` and ``truth`` (UVData), ``layout``, ``gains`` (time, ant, feed), ``scint``
    (2, time) Cyg A's and Cas A's flux factors. ``truth_noise``: the truth's cross-correlations carry radiometer
    noise of the same ``sigma`` too (another realisation), so that the noise weights of both files are the
    radiometer's (a noise-free file's weights follow its modelling error instead)."""
    from pyuvdata import UVData

    from mmflow.sky.sources import get_sources

    rng = np.random.default_rng(seed)
    lay = ovro_lwa_layout("core", radius_m=radius_m)
    x, lam, n = lay.enu, C / freq_hz, lay.n_ant
    tel, _ = _telescope(lay, feeds=("x", "y"))
    dt = SIDEREAL_DAY_S / n_times
    t = np.arange(n_times) * dt
    times = start_jd + t / 86400.0
    pairs = np.array([(i, j) for i in range(n) for j in range(i, n)])
    year = 2000.0 + (start_jd - 2451545.0) / 365.25
    bright = PEELED + SUBTRACTED
    flux = np.array([float(s.flux(freq_hz, year)) for s in get_sources([b[0] for b in bright])])
    dirs = apparent_enu([b[1] for b in bright], [b[2] for b in bright], times, lay)
    sigma = 0.2 * (36.5e6 / freq_hz) ** 2 * np.sqrt(13.0 / max(dt, 13.0))  # an integration averages 13-s samples
    fl = np.repeat(flux[:, None], n_times, 1)
    for k in range(len(PEELED)):
        dirs[k] = _refract(dirs[k], t, rng, freq_hz)
        fl[k] *= np.exp(sigma * rng.normal(size=n_times) - sigma**2 / 2)
    u = np.array(unmodelled, float)
    u_dirs = apparent_enu(u[:, 0], u[:, 1], times, lay)
    u_flux = np.repeat(u[:, 2:], n_times, 1)
    beams = dipole_beams if four else scalar_beam
    truth = point_sum(x, lam, u_dirs, u_flux, pairs, beams)  # (time, bl, correlation)
    sky = point_sum(x, lam, dirs, fl, pairs, beams) + truth
    feeds = [(0, 0), (1, 1), (0, 1), (1, 0)] if four else [(0, 0), (1, 1)]  # the feeds (of i, of j) of each
    # gains (time, ant, feed): a fixed complex gain times a slow drift
    g0 = rng.uniform(0.7, 1.3, (n, 2)) * np.exp(1j * rng.uniform(-np.pi, np.pi, (n, 2)))
    per = rng.uniform(10, 30, (2, n, 2)) * 3600
    ph = rng.uniform(0, 2 * np.pi, (2, n, 2))
    wave = np.sin(2 * np.pi * t[:, None, None, None] / per + ph)  # (time, 2, ant, feed)
    saw_p = rng.uniform(15, 17, (n, 2)) * 60
    saw = (t[:, None, None] / saw_p + rng.uniform(0, 1, (n, 2))) % 1 - 0.5
    ripple = 10 ** (0.1 * rng.uniform(0.8, 1.2, (n, 2)) * saw / 20)  # amplitude: 0.1 dB of power peak to peak
    g = g0 * ripple * (1 + drift[0] * wave[:, 0]) * np.exp(1j * drift[1] * wave[:, 1])
    g = np.broadcast_to(g, (n_times, n, 2))
    i, j = pairs.T
    auto = i == j
    data = np.empty((n_times, len(pairs), len(feeds)), complex)
    for c, (p, q) in enumerate(feeds):
        data[..., c] = g[:, i, p] * np.conj(g[:, j, q]) * (sky[..., c] + np.where(auto & (p == q), T_SYS, 0.0))
    sig = T_SYS / np.sqrt(1e6 * dt)
    fp, fq = [f[0] for f in feeds], [f[1] for f in feeds]
    if noise:
        nz = rng.normal(size=data.shape) + 1j * rng.normal(size=data.shape)
        ai, aj = np.abs(g[:, i][..., fp]), np.abs(g[:, j][..., fq])
        data += np.where(auto[None, :, None], 0, sig / np.sqrt(2) * nz * ai * aj)
    data[:, auto, :2] = data[:, auto, :2].real
    if truth_noise:
        other = np.random.default_rng(seed + 1)
        nz = other.normal(size=truth.shape) + 1j * other.normal(size=truth.shape)
        truth = truth + np.where(auto[None, :, None], 0, sig / np.sqrt(2) * nz)

    def uvdata(d, units, conv, flags):
        rows = (n_times * len(pairs), 1, len(feeds))
        uv = UVData.new(freq_array=np.array([freq_hz]), polarization_array=np.array([-5, -6, -7, -8][:len(feeds)]),
                        times=times,
                        telescope=tel, antpairs=[tuple(p) for p in pairs], do_blt_outer=True,
                        data_array=d.reshape(rows),
                        flag_array=np.broadcast_to(flags[None, :, None], d.shape).reshape(rows),
                        integration_time=dt, channel_width=1e6, vis_units=units, time_axis_faster_than_bls=False)
        uv.pol_convention = conv
        return uv

    # the truth's autocorrelations flagged: calibration gives the data's weight 0 (calibrate.flag_autos)
    return dict(corrupted=uvdata(data, "uncalib", None, np.zeros(len(pairs), bool)),
                truth=uvdata(truth, "Jy", "avg", auto), layout=lay, gains=g, scint=fl[:2] / flux[:2, None])


def radec_vec(ra_deg, dec_deg):
    """The unit vector of ICRS (RA, Dec) in degrees, as the maps' ``products.frame=icrs`` pixels are."""
    from mmflow.conventions import radec_to_vec

    return radec_to_vec(np.deg2rad(ra_deg), np.deg2rad(dec_deg))


def suppression_db(maps, key, nside, stokes=0):
    """Per peeled source (:data:`PEELED`), ``10 log10`` of the largest ``|maps[key] - maps["truth"]|`` within 3 deg
    of it over its Stokes-I peak in ``maps["nopeel"]`` (the same data calibrated, not peeled); the maps are (npix,)
    Stokes I or (4, npix) I, Q, U, V, of which ``stokes`` is compared."""
    import healpy as hp

    from mmflow.analysis.peaks import measure_peak

    def plane(k, i):
        m = maps[k]
        return m if m.ndim == 1 else m[i]

    out = []
    for _, ra, dec in PEELED:
        v = radec_vec(ra, dec)
        peak = measure_peak(plane("nopeel", 0), v, np.deg2rad(10))["peak"]
        pix = hp.query_disc(nside, v, np.deg2rad(3.0))
        out.append(10 * np.log10(np.abs(plane(key, stokes)[pix] - plane("truth", stokes)[pix]).max() / peak))
    return out


def kept_ratios(chain, truth):
    """The :data:`UNMODELLED` sources' peaks in the Stokes-I map ``chain`` over theirs in ``truth``."""
    from mmflow.analysis.peaks import measure_peak

    return np.array([measure_peak(chain, radec_vec(ra, dec), np.deg2rad(10))["peak"]
                     / measure_peak(truth, radec_vec(ra, dec), np.deg2rad(10))["peak"] for ra, dec, _ in UNMODELLED])
