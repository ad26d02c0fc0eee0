"""Write drift scans with pyuvdata (UVH5, MeasurementSet, uvfits), simulated by matvis (an independent simulator)."""
import numpy as np

from mmflow.telescope import ovro_lwa_layout

SIDEREAL_DAY_S = 86164.0905
JD_2023 = 2460000.5  # 2023-02-24: data recorded six years from the config's default epoch (2017)


def gaussian_power_beamfits(path, sigma_rad=0.35, freqs_hz=(39e6, 40e6, 41e6)):
    """A pyuvdata UVBeam power beam (Gaussian) written as beamfits; returns the UVBeam."""
    from pyuvdata.analytic_beam import GaussianBeam

    uvb = GaussianBeam(sigma=sigma_rad, sigma_type="power").to_uvbeam(
        freq_array=np.asarray(freqs_hz), beam_type="power", axis1_array=np.deg2rad(np.arange(0, 360, 1.0)),
        axis2_array=np.deg2rad(np.arange(0, 90.01, 0.5)))
    uvb.write_beamfits(str(path), clobber=True)
    return uvb


def _telescope(lay, feeds=("x",)):
    from astropy import units as u
    from astropy.coordinates import EarthLocation
    from pyuvdata import Telescope
    from pyuvdata.utils import ECEF_from_ENU

    loc = EarthLocation.from_geodetic(lay.lon_deg * u.deg, lay.lat_deg * u.deg, lay.height_m * u.m)
    ecef = ECEF_from_ENU(lay.enu, center_loc=loc) - np.array(
        [loc.x.to_value("m"), loc.y.to_value("m"), loc.z.to_value("m")]
    )
    return Telescope.new(
        "OVRO-LWA-test",
        loc,
        antenna_positions=ecef,
        antenna_names=[f"ANT{k:03d}" for k in range(lay.n_ant)],
        antenna_numbers=list(range(lay.n_ant)),
        instrument="mmflow-test",
        mount_type="fixed",
        feeds=list(feeds),
    ), loc


def matvis_uvdata(beam, n_times=60, radius_m=12.0, freq_hz=40e6,
                  sources=((60.0, 45.0, 500.0), (200.0, 30.0, 400.0), (300.0, 60.0, 450.0)), start_jd=2457802.0,
                  pols=("xx",), yy_gain=1.0, flag_fraction=0.0, seed=0):
    """Point sources (ra, dec, Jy; ICRS degrees) seen for one sidereal day, as one pyuvdata UVData.

    ``beam`` is handed to matvis as is (use a UVBeam power beam: with an analytic E-field beam,
    matvis 1.3 applies the x-feed E-field component rather than the power pattern). With
    ``pols=("xx", "yy")`` the YY data are ``yy_gain`` times XX (a feed-gain difference, so that
    Stokes I = (XX + YY) / 2 differs from either). ``flag_fraction`` of the samples of each
    polarisation are flagged at random (independently per polarisation).
    """
    from astropy.time import Time
    from matvis import simulate_vis
    from pyuvdata import UVData
    from pyuvdata.utils import polstr2num

    lay = ovro_lwa_layout("core", radius_m=radius_m)
    tel, loc = _telescope(lay, feeds=("x", "y") if len(pols) > 1 else ("x",))
    dt = SIDEREAL_DAY_S / n_times
    times = Time(start_jd + np.arange(n_times) * dt / 86400.0, format="jd", scale="utc")
    ra = np.deg2rad([s[0] for s in sources])
    dec = np.deg2rad([s[1] for s in sources])
    flux = np.array([[s[2]] for s in sources])
    n_ant = lay.n_ant
    antpairs = [(i, j) for i in range(n_ant) for j in range(i, n_ant)]
    vis = simulate_vis({k: lay.enu[k] for k in range(n_ant)}, flux, ra, dec, np.array([freq_hz]), times,
                       [beam], loc, precision=2, antpairs=np.array(antpairs))  # (nfreq, ntime, nbl)
    xx = np.transpose(vis, (1, 2, 0)).reshape(n_times * len(antpairs), 1)
    gains = {"xx": 1.0, "yy": yy_gain}
    data = np.stack([xx * gains[p] for p in pols], axis=-1).astype(np.complex128)
    rng = np.random.default_rng(seed)
    flags = rng.random(data.shape) < flag_fraction
    uv = UVData.new(
        freq_array=np.array([freq_hz]),
        polarization_array=np.atleast_1d(polstr2num(list(pols))),
        times=times.jd,
        telescope=tel,
        antpairs=antpairs,
        do_blt_outer=True,
        data_array=data,
        flag_array=flags,
        integration_time=dt,
        channel_width=24e3,
        vis_units="Jy",
        time_axis_faster_than_bls=False,
    )
    uv._fix_autos()
    uv.pol_convention = "sum"  # matvis: an unpolarised source of S Jy gives XX = S B / 2
    return uv, lay


def write_blocks(uv, directory, files=6, stem="scan"):
    """One UVH5 per block of consecutive integrations; returns the paths.

    Selected by baseline-time index (the same rows as selecting the block's times, without
    pyuvdata's per-time matching and LST checks: 2.5 s of 4 for 16 files of 64 x 351 rows)."""
    times = np.unique(uv.time_array)
    paths = []
    for k, block in enumerate(np.array_split(np.arange(len(times)), files)):
        part = uv.select(blt_inds=np.flatnonzero(np.isin(uv.time_array, times[block])), inplace=False)
        path = directory / f"{stem}_{k:03d}.uvh5"
        part.write_uvh5(str(path), clobber=True, fix_autos=True)
        paths.append(path)
    return paths


def matvis_drift_scan(directory, beam, n_times=60, radius_m=12.0, freq_hz=40e6, files=6,
                      sources=((60.0, 45.0, 500.0), (200.0, 30.0, 400.0), (300.0, 60.0, 450.0)), start_jd=2457802.0):
    """:func:`matvis_uvdata` (one polarisation, XX) written as ``files`` UVH5 files."""
    uv, lay = matvis_uvdata(beam, n_times, radius_m, freq_hz, sources, start_jd)
    return write_blocks(uv, directory, files), lay
