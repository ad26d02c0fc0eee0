"""A raw OVRO-LWA day, written in the layout of the real file, calibrated and imaged (issue 24).

The real OVRO-LWA MeasurementSet in ``tests/data`` (read offline) is the template: its 256-antenna
table of which 20 antennas hold data, its site and telescope name (``OVRO_MMA``), its 109 channels
of 24 kHz at 27.4-30.0 MHz and its four polarisations xx, yy, xy, yx. One sidereal day of the
catalogue's 14 sources is simulated on those 20 antennas in ``N_TIMES`` = 130 integrations (the
m-mode stage bins the day into one sidereal bin per integration and needs ``n_bins >= 2 lmax + 1``
= 129 at ``lmax`` = 64; the visibilities hold less than 3e-9 of their power beyond ``m`` = 60, so
nothing aliases from beyond ``n_bins - lmax`` = 66: the longest baseline's ``2 pi |b| / lambda``
is 55, its fringe rate ``2 pi |b_perp| / lambda`` 34; the maps' FWHM, 5.3-7.0 degrees, is the
array's, the same at ``lmax`` = 80), unpolarised
(``XX = YY = sum_s S_s(nu) B(r_s) exp(2 pi i b . r_s / lambda)``, ``XY = YX = 0``), with independent
complex noise on every polarisation and channel of the cross correlations, by mmflow's own
point-source simulator (:func:`mmflow.simulate.visibilities.simulate_drift_scan`, the frame of
date at pyuvdata's LSTs).

Which channels carry the simulated sky: only ``SKY`` = 53-56 (28.656-28.728 MHz), the block that
``input.average_channels=4`` takes around the imaged channel 54 (28.680 MHz, also the one channel
of ``average_channels=1``). Every other channel of the 109 holds the sky of the nearest of them
(53 below, 56 above), its own noise and its own gains: visibilities whose fringes belong to another
frequency, so a run that read any channel outside the block would image a distorted sky.
The calibration model knows two of the 14 sources (Cyg A, Cas A); the other twelve are unmodelled.

The perfect data of the four sky channels are the reference (one UVH5 drift scan in Jy,
``pol_convention`` ``avg``: the simulator's XX is Stokes I through the beam). The raw day is
the same data, every channel, times per-antenna, per-polarisation complex gains
``g_ap(nu) = a_ap b_ap(nu) exp(i (phi_ap + 2 pi nu tau_ap))``, with a smooth bandpass ``b_ap``
(a ripple of 10-25 % and a slope across the subband) and cable delays ``tau_ap`` of 0-600 ns (the
phase turns more than once across the 2.6 MHz), in arbitrary correlator units
(``vis_units`` ``uncalib``, ``pol_convention`` None), ``V_ij^pq -> g_ip conj(g_jq) V_ij^pq``, written
as one MeasurementSet per integration phased to its zenith in FK5 J2000, as the telescope writes
them. ``mmflow run`` with ``calibrate.enabled=true`` images one channel (and an average of four) of
it to the map of the perfect data: every source above 1 % of the brightest peak within 5 % and
within 0.05 FWHM.
"""
import os
import shutil
import tarfile
import tempfile
from pathlib import Path

import healpy
import numpy as np
import pytest
import zarr

from mmflow.analysis.peaks import measure_peak
from mmflow.conventions import radec_to_vec
from mmflow.io.export import write_per_integration
from mmflow.sky.sources import CATALOG, get_sources
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow
from tests.workflow_helpers import ROOT

pytest.importorskip("casacore")
DATA = Path(ROOT) / "tests" / "data"
OVRO = "2018-03-21-01_26_33_0004384620257280_000000_downselected.ms"
QUIET = dict(progress=False, log=lambda *a: None)
N_TIMES, LMAX, CHANNEL, NOISE_JY = 130, 64, 54, 10.0
SKY = np.arange(CHANNEL - 1, CHANNEL + 3)  # the block input.average_channels=4 takes around CHANNEL
BEAM = {"type": "sin_elevation", "alpha": 1.5}


def _template(root):
    from pyuvdata import UVData

    from mmflow.offline import offline_site_registry

    with tarfile.open(DATA / f"{OVRO}.tar.gz") as tar:
        tar.extractall(root, filter="data")
    offline_site_registry()  # OVRO_MMA is unknown to astropy: its location comes from the file
    return UVData.from_file(str(root / OVRO), run_check=False)


def _sky_day(tmpl):
    """One sidereal day on the template's antennas with data: (UVData in Jy, mmflow Telescope, pairs)."""
    from pyuvdata import UVData

    from mmflow.conventions import SIDEREAL_DAY_S
    from mmflow.io.ingest import _antenna_enu
    from mmflow.simulate.scene import sky_points
    from mmflow.simulate.visibilities import simulate_drift_scan
    from mmflow.telescope.array import Telescope
    from mmflow.telescope.beam_factory import make_beam
    from mmflow.telescope.layout import Layout

    ants = np.unique(np.concatenate([tmpl.ant_1_array, tmpl.ant_2_array]))
    used = np.searchsorted(tmpl.telescope.antenna_numbers, ants)
    lat, lon, alt = tmpl.telescope.location_lat_lon_alt_degrees
    layout = Layout([str(tmpl.telescope.antenna_names[k]) for k in used], _antenna_enu(tmpl)[used], lat, lon, alt)
    freqs = tmpl.freq_array.ravel()
    tel = Telescope(layout, make_beam(BEAM), freqs)
    pairs = tel.antenna_pairs()  # (i <= j) of the 20 antennas with data
    dt = SIDEREAL_DAY_S / N_TIMES
    times = tmpl.time_array[0] + np.arange(N_TIMES) * dt / 86400.0
    uv = UVData.new(freq_array=freqs, polarization_array=np.array([-5, -6, -7, -8]), times=times,
                    telescope=tmpl.telescope, antpairs=[(int(ants[i]), int(ants[j])) for i, j in pairs],
                    do_blt_outer=True, integration_time=dt, channel_width=tmpl.channel_width, vis_units="Jy",
                    time_axis_faster_than_bls=False, empty=True)
    uv.extra_keywords = dict(tmpl.extra_keywords)
    lst = uv.lst_array.reshape(N_TIMES, len(pairs))[:, 0]
    epoch = float(np.median(times))
    sky = np.stack([simulate_drift_scan(tel, freqs[c], lst, sky_points(tel, freqs[c], epoch, sources=list(CATALOG)),
                                        pairs) for c in SKY], axis=-1)  # (time, baseline, sky channel)
    vis = sky[:, :, np.clip(np.arange(len(freqs)), SKY[0], SKY[-1]) - SKY[0]]  # nearest sky channel's sky
    rng = np.random.default_rng(24)
    noise = NOISE_JY * (rng.normal(size=vis.shape + (4,)) + 1j * rng.normal(size=vis.shape + (4,)))
    noise[:, pairs[:, 0] == pairs[:, 1]] = 0
    data = noise + np.stack([vis, vis, 0 * vis, 0 * vis], axis=-1)
    uv.data_array = data.reshape(N_TIMES * len(pairs), len(freqs), 4)
    uv.pol_convention = "avg"  # the simulator's XX is Stokes I through the beam
    return uv, tel, pairs


def _gains(freqs, n_ant, rng):
    """``g[a, p, nu]``: amplitude x bandpass x exp(i (phase + 2 pi nu tau)), in correlator units."""
    x = (freqs - freqs.mean()) / np.ptp(freqs)  # -0.5 .. 0.5 across the subband
    shape = (n_ant, 2, 1)
    amp = 3e-3 * np.exp(rng.uniform(np.log(0.5), np.log(2.0), shape))
    band = (1 + rng.uniform(0.1, 0.25, shape) * np.sin(2 * np.pi * rng.uniform(0.5, 1.5, shape) * x
                                                       + rng.uniform(0, 2 * np.pi, shape))
            + rng.uniform(-0.2, 0.2, shape) * x)
    tau = rng.uniform(0.0, 600e-9, shape)
    return amp * band * np.exp(1j * (rng.uniform(-np.pi, np.pi, shape) + 2 * np.pi * freqs * tau)), tau


@pytest.fixture(scope="module")
def day(tmp_path_factory):
    root = tmp_path_factory.mktemp("rawday")
    tmpl = _template(root)
    uv, tel, pairs = _sky_day(tmpl)
    uv.select(freq_chans=SKY, inplace=False).write_uvh5(str(root / "perfect.uvh5"), clobber=True, fix_autos=True)
    rng = np.random.default_rng(7)
    g, tau = _gains(uv.freq_array.ravel(), tel.n_ant, rng)
    i = np.tile(pairs[:, 0], N_TIMES)
    j = np.tile(pairs[:, 1], N_TIMES)
    for k, (p, q) in enumerate(((0, 0), (1, 1), (0, 1), (1, 0))):  # xx, yy, xy, yx
        uv.data_array[:, :, k] *= g[i, p] * np.conj(g[j, q])
    uv._fix_autos()  # |g_i|^2 V_ii is real: drop the product's rounding
    uv.vis_units, uv.pol_convention = "uncalib", None  # pyuvdata: uncalibrated data have no convention
    # casacore syncs every table it creates: on a disk that is ~0.4 s per MS, on tmpfs ~0.04 s
    shm = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
    ms_dir = Path(tempfile.mkdtemp(prefix="mmflow-rawday-", dir=shm))
    write_per_integration(uv, ms_dir, "ms", phase_frame="fk5")
    yield {"root": root, "ms": ms_dir, "gains": g, "tau": tau, "tel": tel, "tmpl": tmpl,
           "freq_hz": float(uv.freq_array.ravel()[CHANNEL])}
    shutil.rmtree(ms_dir, ignore_errors=True)


def test_raw_day_is_in_the_telescope_layout(day):
    """What the test wrote is what the OVRO-LWA writes: the template's metadata, one integration
    per MeasurementSet phased to its own zenith in FK5 J2000, 109 channels, four polarisations,
    uncalibrated; the delays wrap the phase across the subband."""
    from pyuvdata import UVData

    tmpl = day["tmpl"]
    files = sorted(day["ms"].glob("*.ms"))
    assert len(files) == N_TIMES
    uv = UVData.from_file(str(files[N_TIMES // 3]), run_check=False)
    assert uv.Ntimes == 1 and uv.Nfreqs == 109 and uv.Nants_data == 20
    assert uv.telescope.name == tmpl.telescope.name and uv.telescope.Nants == tmpl.telescope.Nants == 256
    np.testing.assert_array_equal(uv.polarization_array, tmpl.polarization_array)
    np.testing.assert_allclose(uv.freq_array, tmpl.freq_array)
    assert uv.vis_units == "uncalib" and uv.pol_convention is None
    (cat,) = uv.phase_center_catalog.values()
    assert cat["cat_type"] == "sidereal" and cat["cat_frame"] == "fk5" and cat["cat_epoch"] == 2000.0
    zenith_dec = np.deg2rad(tmpl.telescope.location_lat_lon_alt_degrees[0])
    assert abs(cat["cat_lat"] - zenith_dec) < np.deg2rad(0.5)  # the zenith, up to precession since J2000
    span = np.ptp(uv.freq_array) * np.abs(day["tau"][:, :, 0] - day["tau"][0, 0, 0])
    assert span.max() > 1.0  # cycles of baseline phase across the subband


def _cfg(run_dir, data, freq_hz, *extra):
    return load_config("workflows/uvh5-image.yaml", [
        f"run.directory={run_dir}", f"input.path={data}", f"mmode.lmax={LMAX}", "transfer.dtype=float64",
        f"observation.freqs_mhz=[{freq_hz / 1e6:.6f}]", "imaging.lcurve=false", "products.nside=64",
        "products.png=false", "products.flux_scale=false", "cluster.kind=synchronous",
        "beam={type: sin_elevation, alpha: 1.5}", *extra])


def _map(run_dir):
    return healpy.read_map(str(next((run_dir / "maps").glob("map_*.fits"))))


@pytest.mark.parametrize("average", [1, 4])
def test_raw_day_calibrates_to_the_perfect_map(day, tmp_path, average):
    """Every source whose flux is above 1 % of the brightest's (the eight the paper removes; fainter ones
    sit at the level of the bright sources' sidelobes on 20 antennas) within 5 % and 0.05 FWHM."""
    ref, cal = tmp_path / "ref", tmp_path / "cal"
    extra = [f"input.average_channels={average}"]
    run_workflow(_cfg(ref, day["root"] / "perfect.uvh5", day["freq_hz"], *extra), **QUIET)
    run_workflow(_cfg(cal, day["ms"] / "*.ms", day["freq_hz"], "calibrate.enabled=true", *extra), **QUIET)
    gains = zarr.open_group(str(cal / "gains.zarr"), mode="r")
    assert not gains["flags"][:].any()
    store = zarr.open_group(str(cal / "vis.zarr"), mode="r")
    assert store.attrs["cross_pols"] == ["xy", "yx"] and store["vis"].shape[2] == 1
    if average == 1:  # the solution is the truth up to one phase per polarisation
        solved = gains["gains"][0, 0]  # (antenna, pol)
        truth = day["gains"][:, :, CHANNEL]
        ratio = solved / truth
        ratio /= ratio[0] / np.abs(ratio[0])
        print(f"solved / true gains: amplitude {np.abs(ratio).min():.4f}-{np.abs(ratio).max():.4f}, "
              f"phase within {np.abs(np.angle(ratio)).max():.4f} rad")
        np.testing.assert_allclose(ratio, 1.0, atol=0.03)
    m_ref, m_cal = _map(ref), _map(cal)
    srcs = get_sources(list(CATALOG))
    flux = {s.name: float(s.flux(day["freq_hz"])) for s in srcs}
    peaks = {}
    for s in srcs:
        if flux[s.name] < 0.01 * max(flux.values()):
            continue
        v = radec_to_vec(np.deg2rad(s.ra_deg), np.deg2rad(s.dec_deg))
        a, b = measure_peak(m_ref, v, np.deg2rad(4.0)), measure_peak(m_cal, v, np.deg2rad(4.0))
        offset = np.arccos(np.clip(np.dot(a["vec"], b["vec"]), -1, 1)) / a["fwhm_rad"]
        peaks[s.name] = (b["peak"] / a["peak"], offset)
    print(f"average {average}: calibrated / perfect peak, offset (FWHM):",
          {k: (round(float(r), 4), round(float(o), 4)) for k, (r, o) in peaks.items()})
    assert len(peaks) == 8
    np.testing.assert_allclose([r for r, _ in peaks.values()], 1.0, atol=0.05)
    assert max(o for _, o in peaks.values()) < 0.05
