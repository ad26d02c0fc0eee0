"""The three real files of pyuvdata's test-data repository (tests/data/README.md), ingested offline.

Each is read with the network blocked (sockets refuse to connect, astropy's downloader fails the
test, astropy's site list starts empty) and must equal pyuvdata's own read followed by
``unproject_phase``: the OVRO-LWA MeasurementSet (telescope ``OVRO_MMA``, 256-antenna table with 20
antennas holding data, 109 channels, xx/yy/xy/yx, phased to the zenith in FK5 J2000, uncalibrated),
the LWA-SV MeasurementSet (telescope ``LWASV``, which astropy does not know: its location is the
file's own antenna positions) and the HERA UVH5 drift scan (uncalibrated). A full run on the
single 13 s OVRO-LWA integration is refused before any work.
"""
import socket
import tarfile
from pathlib import Path

import numpy as np
import pytest

from mmflow.cli import main
from tests.rawfile_helpers import ingest, pyuvdata_reference
from tests.workflow_helpers import ROOT

DATA = Path(ROOT) / "tests" / "data"
OVRO = "2018-03-21-01_26_33_0004384620257280_000000_downselected.ms"
LWASV = "test_adp4_0_00300673800807520000_58342_05_00_14.ms"
HERA = "zen.2458661.23480.HH.uvh5"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("real")
    for name in (OVRO, LWASV):
        with tarfile.open(DATA / f"{name}.tar.gz") as tar:
            tar.extractall(root, filter="data")
    return {"ovro": root / OVRO, "lwasv": root / LWASV, "hera": DATA / HERA}


@pytest.fixture
def offline(monkeypatch):
    """No network: connecting a socket raises, astropy's downloader fails the test, and astropy's
    site registry is empty (as in a fresh process) so a lookup would have to download it."""
    import astropy.utils.data
    from astropy.coordinates import EarthLocation

    def refuse(*args, **kwargs):
        raise AssertionError(f"network access attempted: {args[:2]}")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(astropy.utils.data, "download_file", refuse)
    monkeypatch.setattr(EarthLocation, "_site_registry", None)


@pytest.mark.parametrize("name", ["ovro", "lwasv", "hera"])
def test_real_file_ingested_offline_equals_pyuvdata_read_and_unprojection(files, offline, tmp_path, name):
    g = ingest(files[name], tmp_path / "run", "input.nonfinite=flag")  # LWA-SV's autos hold NaN
    uv, ants, pairs, vis, w = pyuvdata_reference(files[name])
    assert g.attrs["pols"] == ["xx", "yy"]
    np.testing.assert_array_equal(g["antenna_numbers"][:], uv.telescope.antenna_numbers[np.searchsorted(
        uv.telescope.antenna_numbers, ants)])
    np.testing.assert_array_equal(g["pairs"][:], pairs)
    assert g["antenna_enu"].shape == (len(ants), 3)  # only the antennas with data, whatever the table lists
    np.testing.assert_allclose(g["freqs_hz"][:], uv.freq_array.ravel())
    np.testing.assert_array_equal(g["weights"][:], w)
    scale = np.abs(vis).max()
    np.testing.assert_allclose(g["vis"][:], vis, rtol=0, atol=4 * np.finfo(np.float32).eps * scale)
    lat, lon, _ = uv.telescope.location_lat_lon_alt_degrees
    assert abs(g.attrs["lat_deg"] - lat) < 1e-9 and abs(g.attrs["lon_deg"] - lon) < 1e-9
    np.testing.assert_allclose(g["lst"][:], np.unique(uv.lst_array), rtol=0, atol=1e-9)
    if name == "hera":
        assert "vis_cross" not in g and g.attrs["cross_pols"] == []
    else:  # xy and yx carried beside xx and yy
        assert g.attrs["cross_pols"] == ["xy", "yx"]
        _, _, _, xvis, xw = pyuvdata_reference(files[name], pols=(-7, -8))
        np.testing.assert_array_equal(g["weights_cross"][:], xw)
        np.testing.assert_allclose(g["vis_cross"][:], xvis, rtol=0, atol=4 * np.finfo(np.float32).eps * scale)
        assert np.abs(xvis).max() > 0 and np.abs(xvis.imag).max() > 0
        parallel_only = ingest(files[name], tmp_path / "no_cross", "input.nonfinite=flag", "input.cross_hands=false")
        assert "vis_cross" not in parallel_only  # what every stage reads is the same, bit for bit
        for key in ("vis", "weights", "autos", "lst"):
            np.testing.assert_array_equal(parallel_only[key][:], g[key][:], err_msg=key)


def test_layouts_of_the_real_files(files, offline):
    """OVRO_MMA: 20 of 256 antennas hold data; LWASV: astropy does not know it, so pyuvdata places it
    at the mean of its antenna positions (near the LWA-SV station, Sevilleta, New Mexico)."""
    from mmflow.io.ingest import plan_ingest

    plan_ingest.cache_clear()
    ovro = plan_ingest(str(files["ovro"]), None, "error", True)
    assert len(ovro.ant_numbers) == 20 and ovro.freqs_hz.size == 109 and ovro.n_time == 1
    assert ovro.file_info[0]["phase"] == "phased" and ovro.file_info[0]["vis_units"] == "uncalib"
    lwasv = plan_ingest(str(files["lwasv"]), None, "error", True)
    assert abs(lwasv.layout.lat_deg - 34.348) < 0.01 and abs(lwasv.layout.lon_deg + 106.886) < 0.01


def test_uncalibrated_file_refused_without_calibration_naming_calibrate_enabled(files, offline, tmp_path, capsys):
    rc = main(["run", "workflows/uvh5-image.yaml", f"run.directory={tmp_path / 'run'}",
               f"input.path={files['hera']}", "cluster.kind=synchronous"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert "vis_units" in err and "uncalib" in err and "calibrate.enabled=true" in err, err
    assert not (tmp_path / "run" / "vis.zarr").exists()


def test_full_run_on_one_snapshot_refused_before_any_work(files, offline, tmp_path, capsys):
    rc = main(["run", "workflows/uvh5-image.yaml", f"run.directory={tmp_path / 'run'}",
               f"input.path={files['ovro']}", "cluster.kind=synchronous", "calibrate.enabled=true"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert "1 integration(s) of 13 s" in err and "sidereal bins" in err and "mmode.min_coverage" in err, err
    assert not (tmp_path / "run" / "vis.zarr").exists() and not (tmp_path / "run" / "config.yaml").exists()


def test_the_papers_workflow_on_a_raw_ovro_lwa_file(files, offline, tmp_path, capsys):
    """workflows/ovro-lwa-2017.yaml pointed at the real raw file: the paper's channels (36-73 MHz) are not
    in this 27.4-30.0 MHz subband (refused naming the nearest channels); a channel it holds gets as far as
    the coverage check (one 13 s integration cannot make m-modes), before any work, without a traceback."""
    base = ["run", "workflows/ovro-lwa-2017.yaml", f"run.directory={tmp_path / 'run'}", f"input.path={files['ovro']}",
            "cluster.kind=synchronous"]
    assert main(base) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "observation.freqs_mhz" in err and "MHz" in err, err
    assert main(base + ["observation.freqs_mhz=[29.0]"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "sidereal bins" in err and "mmode.min_coverage" in err, err
    assert not (tmp_path / "run" / "vis.zarr").exists()
