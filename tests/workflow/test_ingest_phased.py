"""Phased multi-integration files equal the drift scan they were made from: a short drift scan written
as UVH5 (unprojected), then phased with pyuvdata to one fixed sidereal centre 10 deg from the zenith
and written as a MeasurementSet and as uvfits; all three ingest to the same vis.zarr (the MS through
mmflow's casacore reader, the uvfits through pyuvdata's read and unproject_phase)."""
import numpy as np
import pytest

from mmflow.bench.ingest import _scan
from tests.rawfile_helpers import ingest

EPS = 4 * np.finfo(np.float32).eps


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    pytest.importorskip("casacore")
    root = tmp_path_factory.mktemp("phased")
    uv = _scan(n_ant=8, n_freq=4, n_time=12, seed=5)
    uv.flag_array[::7, 1] = True
    uv.write_uvh5(str(root / "drift.uvh5"))
    mid = np.unique(uv.lst_array)[len(np.unique(uv.lst_array)) // 2]
    lat = uv.telescope.location.lat.rad
    drift = uv.data_array.copy()
    uv.phase(ra=mid + np.deg2rad(6.0), dec=lat - np.deg2rad(8.0), epoch="J2000", cat_name="fixed")
    cross = uv.ant_1_array != uv.ant_2_array
    assert np.median(np.abs(np.angle(uv.data_array[cross] * np.conj(drift[cross])))) > 0.3  # phasing matters
    uv.write_ms(str(root / "phased.ms"))
    uv.write_uvfits(str(root / "phased.uvfits"))
    return root


def test_phased_ms_and_uvfits_equal_the_drift_uvh5(files, tmp_path):
    ref = ingest(files / "drift.uvh5", tmp_path / "drift")
    assert ref.attrs["ingest_file_info"][0]["phase"] == "drift"
    scale = np.abs(ref["vis"][:]).max()
    for name in ("phased.ms", "phased.uvfits"):
        g = ingest(files / name, tmp_path / name)
        assert g.attrs["ingest_file_info"][0]["phase"] == "phased", name
        for key in ("pairs", "freqs_hz"):
            np.testing.assert_array_equal(g[key][:], ref[key][:], err_msg=name)
        np.testing.assert_array_equal(g["weights"][:], ref["weights"][:], err_msg=name)
        np.testing.assert_allclose(g["lst"][:], ref["lst"][:], rtol=0, atol=1e-8, err_msg=name)
        np.testing.assert_allclose(g["vis"][:], ref["vis"][:], rtol=0, atol=EPS * scale, err_msg=name)
        phased_by = np.abs(np.angle(g["vis"][:] * np.conj(ref["vis"][:])))
        assert np.max(phased_by) < 1e-5, name
