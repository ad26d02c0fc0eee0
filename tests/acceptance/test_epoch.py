"""Data recorded far from the default epoch (2017) land where they belong: the data's own epoch is used.

matvis (independent of mmflow) simulates a drift scan recorded in 2030 (13 years after the
config's default epoch); ingest stores the data's epoch and every frame rotation uses it.
Rotating with the 2017 default instead shifts the sources by the 13 years of precession
(~11'), which the same measurement detects: the test can fail.
"""
import healpy
import numpy as np
import pytest
import zarr

from mmflow.analysis.peaks import measure_peak
from mmflow.conventions import healpy_alm, radec_to_vec
from mmflow.imaging.maps import alm_to_output_map
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow
from tests.uvh5_helpers import gaussian_power_beamfits, matvis_drift_scan

SOURCES = ((60.0, 45.0, 500.0), (200.0, 30.0, 400.0), (300.0, 60.0, 450.0))
JD_2030 = 2462502.5


@pytest.fixture(scope="module")
def run_2030(tmp_path_factory):
    root = tmp_path_factory.mktemp("epoch")
    beam_file = str(root / "beam.fits")
    beam = gaussian_power_beamfits(beam_file)
    (root / "uvh5").mkdir()
    matvis_drift_scan(root / "uvh5", beam, n_times=240, radius_m=30.0, sources=SOURCES, start_jd=JD_2030, files=4)
    cfg = load_config("workflows/uvh5-image.yaml", [
        f"run.directory={root / 'run'}", f"input.path={root / 'uvh5' / '*.uvh5'}", "mmode.lmax=96",
        "transfer.dtype=float64", "transfer.m_block=16", "imaging.eps=0.0001", "transfer.noise_weighting=false",
        "imaging.filter_m0=false", "imaging.lcurve=false", "products.nside=256", "products.unit=Jy/sr",
        "products.frame=icrs", "cluster.kind=synchronous", f"beam={{type: pyuvdata, file: {beam_file}}}"])
    run_workflow(cfg, progress=False, log=lambda *a: None)
    return root / "run"


def _offsets(hmap):
    out = []
    for ra, dec, _ in SOURCES:
        pk = measure_peak(hmap, radec_to_vec(np.deg2rad(ra), np.deg2rad(dec)), np.deg2rad(10))
        out.append(pk["offset_rad"] / pk["fwhm_rad"])
    return np.array(out)


def test_data_from_2030_image_at_their_icrs_positions(run_2030):
    vis = zarr.open_group(str(run_2030 / "vis.zarr"), mode="r")
    assert abs(vis.attrs["epoch_jd"] - (JD_2030 + 0.5)) < 1.0  # the data's epoch, not the config's 2017
    hmap = healpy.read_map(str(run_2030 / "maps" / "map_40.000MHz.fits"))
    header = dict(healpy.read_map(str(run_2030 / "maps" / "map_40.000MHz.fits"), h=True)[1])
    assert header["EPOCHJD"] == vis.attrs["epoch_jd"]
    good = _offsets(hmap)
    assert np.all(good < 0.01), good
    # the same alm rotated with the config's default epoch (2017) is off by the precession
    alm = healpy_alm(zarr.open_group(str(run_2030 / "alm.zarr"))["alm"][0, 0], 96, 96)
    wrong = _offsets(alm_to_output_map(alm, 96, 40e6, 2457802.0, "icrs", "Jy/sr", 256))
    assert wrong.max() > 0.02 and np.all(wrong > 3 * good), (good, wrong)  # measured 0.009-0.038 vs <= 0.0015


def test_frame_rotations_are_exact_inverses_of_each_other():
    """A map rotated to Galactic and back comes home: astropy's two directions differ by ~3"
    (aberration), so each pair is fitted once and the reverse is its transpose."""
    from mmflow.sky.frames import rotation_matrix

    for a, b in (("date", "galactic"), ("date", "icrs"), ("icrs", "galactic")):
        fwd, back = rotation_matrix(a, b, 2461000.5), rotation_matrix(b, a, 2461000.5)
        assert np.array_equal(back, fwd.T)
        assert np.allclose(fwd @ fwd.T, np.eye(3), atol=1e-14)


def test_simulated_times_are_the_utc_of_their_lsts(tmp_path):
    """vis.zarr's time_jd and lst describe the same instants (an exported file's reader recomputes
    the LST from the time), here in 2026, far from the default epoch."""
    from pyuvdata.utils import get_lst_for_time

    from tests.workflow_helpers import small_config

    cfg = small_config(tmp_path / "run", "observation.epoch_jd=2461000.5", "sky.diffuse=false")
    run_workflow(cfg, only=["simulate"], progress=False, log=lambda *a: None)
    g = zarr.open_group(str(tmp_path / "run" / "vis.zarr"), mode="r")
    t, lst, a = g["time_jd"][:], g["lst"][:], g.attrs
    site_lst = get_lst_for_time(t, latitude=a["lat_deg"], longitude=a["lon_deg"], altitude=a["height_m"])
    assert np.abs(np.angle(np.exp(1j * (site_lst - lst)))).max() < 1e-7
    assert abs(np.median(t) - 2461000.5) < 0.51  # the day around the epoch
    assert np.all(np.diff(t) > 0)
