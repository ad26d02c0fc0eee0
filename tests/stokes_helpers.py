"""A full-Stokes drift scan (xx, yy, xy, yx) of polarised point sources written as UVH5 by pyuvdata.

The visibilities come from :func:`mmflow.simulate.polarised.simulate_polarised_drift_scan`, the
measurement equation summed directly per integration (independent of the transfer-matrix code),
at the LSTs pyuvdata gives the files' times, so that ingest's own LSTs (from the times) see them.
Sources are given in the frame of date (a run with ``products.frame=date`` images them where they
are given).
"""
import numpy as np

from mmflow.conventions import radec_to_vec
from mmflow.simulate.polarised import PolarisedPoints, simulate_polarised_drift_scan
from mmflow.telescope import Telescope
from mmflow.telescope.jones import ShortDipoleJones
from tests.polarised_fields import TAPER, correlate
from tests.polarised_scene import scene_layout
from tests.uvh5_helpers import SIDEREAL_DAY_S, _telescope, write_blocks

#: sources (ra, dec in the frame of date, degrees; I Jy; Q/I, U/I, V/I)
SOURCES = ((30.0, 60.0, 100.0, 0.3, 0.2, 0.05), (120.0, 20.0, 80.0, -0.1, 0.4, -0.1),
           (200.0, 45.0, 120.0, 0.0, 0.0, 0.0), (290.0, 5.0, 90.0, -0.4, -0.1, 0.5))
HORIZON_TAPER = 3.0


def compact_layout(n_ant=10, radius_m=8.0):
    """The full-Stokes scene's array (:func:`tests.polarised_scene.scene_layout`), ``n_ant`` antennas within
    ``radius_m``."""
    return scene_layout(n_ant, radius_m)


def sky(sources=SOURCES):
    s = np.asarray(sources, float)
    vec = radec_to_vec(np.deg2rad(s[:, 0]), np.deg2rad(s[:, 1]))
    return PolarisedPoints(vec, np.c_[s[:, 2], s[:, 2:3] * s[:, 3:6]])


def polarised_uvh5(directory, freqs_hz=(40e6, 41e6), n_times=240, files=4, start_jd=2457802.0, layout=None,
                   sources=SOURCES, fields=False):
    """Write the scan as ``files`` UVH5 files; returns ``(paths, layout, sky)``.

    ``fields``: the visibilities from real electric fields in the time domain
    (:func:`tests.polarised_fields.correlate`: nothing of mmflow's simulator, coherency or Stokes conventions)
    instead of :func:`mmflow.simulate.polarised.simulate_polarised_drift_scan`.
    """
    from astropy.time import Time
    from pyuvdata import UVData
    from pyuvdata.utils import get_lst_for_time

    lay = layout or compact_layout()
    tel, _ = _telescope(lay, feeds=("x", "y"))
    dt = SIDEREAL_DAY_S / n_times
    times = start_jd + np.arange(n_times) * dt / 86400.0
    lsts = get_lst_for_time(times, latitude=lay.lat_deg, longitude=lay.lon_deg, altitude=lay.height_m)
    jones = ShortDipoleJones(horizon_taper=HORIZON_TAPER)
    mtel = Telescope(lay, jones.power_beam(), list(freqs_hz))
    n_ant = lay.n_ant
    pairs = np.array([(i, j) for i in range(n_ant) for j in range(i, n_ant)])
    src = sky(sources)
    if fields:
        assert HORIZON_TAPER == TAPER  # the fields' dipoles are the imaging beam's
        vis = np.stack([correlate(lay.enu, f, np.deg2rad(lay.lat_deg), lsts, list(zip(src.stokes_jy, src.vectors)),
                                  pairs) for f in freqs_hz], axis=-1)
    else:
        vis = np.stack([simulate_polarised_drift_scan(mtel, jones, f, lsts, src, pairs=pairs) for f in freqs_hz],
                       axis=-1)  # (time, corr [xx, yy, xy, yx], bl, freq)
    data = np.transpose(vis, (0, 2, 3, 1)).reshape(n_times * len(pairs), len(freqs_hz), 4)
    uv = UVData.new(freq_array=np.asarray(freqs_hz, float), polarization_array=np.array([-5, -6, -7, -8]),
                    times=Time(times, format="jd", scale="utc").jd, telescope=tel,
                    antpairs=[tuple(p) for p in pairs], do_blt_outer=True, data_array=data,
                    flag_array=np.zeros(data.shape, bool), integration_time=dt, channel_width=24e3,
                    vis_units="Jy", time_axis_faster_than_bls=False)
    uv.pol_convention = "avg"  # an unpolarised source of S Jy gives XX = YY = S through a unit feed
    return write_blocks(uv, directory, files, stem="stokes"), lay, src
