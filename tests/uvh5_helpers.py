"""Write drift scans as UVH5 with pyuvdata, simulated by matvis (an independent simulator)."""
import numpy as np

from mmflow.telescope import ovro_lwa_layout

SIDEREAL_DAY_S = 86164.0905


def gaussian_power_beamfits(path, sigma_rad=0.35, freqs_hz=(39e6, 40e6, 41e6)):
    """A pyuvdata UVBeam power beam (Gaussian) written as beamfits; returns the UVBeam."""
    from pyuvdata.analytic_beam import GaussianBeam

    uvb = GaussianBeam(sigma=sigma_rad, sigma_type="power").to_uvbeam(
        freq_array=np.asarray(freqs_hz), beam_type="power", axis1_array=np.deg2rad(np.arange(0, 360, 1.0)),
        axis2_array=np.deg2rad(np.arange(0, 90.01, 0.5)))
    uvb.write_beamfits(str(path), clobber=True)
    return uvb


def matvis_drift_scan(directory, beam, n_times=60, radius_m=12.0, freq_hz=40e6, files=6,
                      sources=((60.0, 45.0, 500.0), (200.0, 30.0, 400.0), (300.0, 60.0, 450.0)), start_jd=2457802.0):
    """Point sources (ra, dec, Jy; ICRS degrees) seen for one sidereal day; one UVH5 per block of times.

    ``beam`` is handed to matvis as is (use a UVBeam power beam: with an analytic E-field beam,
    matvis 1.3 applies the x-feed E-field component rather than the power pattern).
    """
    from astropy import units as u
    from astropy.coordinates import EarthLocation
    from astropy.time import Time
    from matvis import simulate_vis
    from pyuvdata import Telescope, UVData
    from pyuvdata.utils import ECEF_from_ENU

    lay = ovro_lwa_layout("core", radius_m=radius_m)
    loc = EarthLocation.from_geodetic(lay.lon_deg * u.deg, lay.lat_deg * u.deg, lay.height_m * u.m)
    dt = SIDEREAL_DAY_S / n_times
    times = Time(start_jd + np.arange(n_times) * dt / 86400.0, format="jd", scale="utc")
    ra = np.deg2rad([s[0] for s in sources])
    dec = np.deg2rad([s[1] for s in sources])
    flux = np.array([[s[2]] for s in sources])
    n_ant = lay.n_ant
    antpairs = [(i, j) for i in range(n_ant) for j in range(i, n_ant)]
    vis = simulate_vis({k: lay.enu[k] for k in range(n_ant)}, flux, ra, dec, np.array([freq_hz]), times,
                       [beam], loc, precision=2, antpairs=np.array(antpairs))  # (nfreq, ntime, nbl)
    ecef = ECEF_from_ENU(lay.enu, center_loc=loc) - np.array([loc.x.to_value('m'), loc.y.to_value('m'), loc.z.to_value('m')])
    tel = Telescope.new("OVRO-LWA-test", loc, antenna_positions=ecef,
                        antenna_names=[f"ANT{k:03d}" for k in range(n_ant)], antenna_numbers=list(range(n_ant)),
                        instrument="mmflow-test", mount_type="fixed", feeds=["x"])
    data = np.transpose(vis, (1, 2, 0)).reshape(n_times * len(antpairs), 1, 1)
    uv = UVData.new(freq_array=np.array([freq_hz]), polarization_array=["xx"], times=times.jd, telescope=tel,
                    antpairs=antpairs, do_blt_outer=True, data_array=data.astype(np.complex128),
                    integration_time=dt, channel_width=24e3, vis_units="Jy", time_axis_faster_than_bls=False)
    paths = []
    for k, block in enumerate(np.array_split(np.arange(n_times), files)):
        part = uv.select(times=times.jd[block], inplace=False)
        path = directory / f"scan_{k:03d}.uvh5"
        part.write_uvh5(str(path), clobber=True, fix_autos=True)
        paths.append(path)
    return paths, lay
