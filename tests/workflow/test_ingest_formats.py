"""MeasurementSets (one per integration, as the OVRO-LWA writes them) and uvfits ingest to the same
``vis.zarr`` as UVH5, and image to the same map. Data: matvis through pyuvdata, recorded in 2023, XX and
YY with different gains and independent flags."""
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import zarr

from mmflow.io.export import write_per_integration
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow
from tests.uvh5_helpers import JD_2023, gaussian_power_beamfits, matvis_uvdata, write_blocks

pytest.importorskip("casacore")
SOURCES = ((60.0, 45.0, 500.0), (200.0, 30.0, 400.0), (300.0, 60.0, 450.0))
F32 = np.finfo(np.float32).eps


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    root = tmp_path_factory.mktemp("formats")
    beam_file = root / "gauss_power.fits"
    beam = gaussian_power_beamfits(beam_file)
    uv, _ = matvis_uvdata(beam, n_times=72, radius_m=20.0, sources=SOURCES, start_jd=JD_2023,
                          pols=("xx", "yy"), yy_gain=0.9, flag_fraction=0.02, seed=5)
    (root / "uvh5").mkdir()
    write_blocks(uv, root / "uvh5", files=6)
    # casacore syncs every table it creates: on a disk that is ~0.4 s per MS, on tmpfs ~0.04 s
    shm = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
    ms_dir = Path(tempfile.mkdtemp(prefix="mmflow-ms-", dir=shm))
    write_per_integration(uv, ms_dir, "ms")
    first = np.unique(uv.time_array)[:12]
    for fmt in ("uvfits", "uvh5"):
        (root / f"{fmt}_12").mkdir()
        write_per_integration(uv, root / f"{fmt}_12", fmt, times=first)
    yield {"root": root, "beam": beam_file, "ms": ms_dir, "uv": uv}
    shutil.rmtree(ms_dir, ignore_errors=True)


def _cfg(scan, run_dir, pattern, *extra):
    return load_config("workflows/uvh5-image.yaml", [
        f"run.directory={run_dir}", f"input.path={pattern}", "mmode.lmax=32", "transfer.dtype=float64",
        "transfer.m_block=8", "imaging.eps=0.0001", "transfer.noise_weighting=false", "imaging.filter_m0=false",
        "products.nside=32", "products.png=false", "products.unit=Jy/sr", "cluster.kind=synchronous",
        f"beam={{type: pyuvdata, file: {scan['beam']}}}", *extra])


def _ingest(scan, run_dir, pattern):
    run_workflow(_cfg(scan, run_dir, pattern), only=["ingest"], progress=False, log=lambda *a: None)
    return zarr.open_group(str(run_dir / "vis.zarr"), mode="r")


def _same_store(a, b):
    """Same rows, baselines, weights; visibilities within float32 rounding; same times and LSTs."""
    np.testing.assert_array_equal(a["pairs"][:], b["pairs"][:])
    np.testing.assert_array_equal(a["freqs_hz"][:], b["freqs_hz"][:])
    np.testing.assert_allclose(a["antenna_enu"][:], b["antenna_enu"][:], atol=1e-6)
    np.testing.assert_allclose(a["time_jd"][:], b["time_jd"][:], rtol=0, atol=1e-6 / 86400)  # 1 us
    np.testing.assert_allclose(a["lst"][:], b["lst"][:], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(a["weights"][:], b["weights"][:])
    va, vb = a["vis"][:], b["vis"][:]
    assert np.max(np.abs(va - vb)) <= 4 * F32 * np.max(np.abs(va))


def test_ms_per_integration_ingests_to_the_uvh5_store_and_map(scan, tmp_path):
    import healpy

    uvh5 = _ingest(scan, tmp_path / "h", str(scan["root"] / "uvh5" / "*.uvh5"))
    ms = _ingest(scan, tmp_path / "m", str(scan["ms"] / "*.ms"))
    assert len(ms.attrs["files"]) == 72 and ms.attrs["ingest_file_info"][0]["phase"] == "phased"
    _same_store(uvh5, ms)
    # XX and YY kept as they are (Stokes I is formed after calibration, where the data are read),
    # each with its own flags: against the simulation itself
    from mmflow.io.polarization import stokes_i

    uv = scan["uv"]
    assert ms.attrs["pols"] == ["xx", "yy"]
    # the MeasurementSets carry matvis's 'sum' convention through pyuvdata: doubled on ingest, as the UVH5
    assert ms.attrs["pol_convention"] == uvh5.attrs["pol_convention"] == "sum" and ms.attrs["pol_factor"] == 2.0
    for p in range(2):
        vp = 2.0 * uv.data_array[:, 0, p].reshape(uv.Ntimes, uv.Nbls)
        fp = uv.flag_array[:, 0, p].reshape(uv.Ntimes, uv.Nbls)
        np.testing.assert_array_equal(ms["weights"][:, :, 0, p] == 0, fp)
        np.testing.assert_allclose(ms["vis"][:, :, 0, p][~fp], vp[~fp], rtol=0, atol=4 * F32 * np.abs(vp).max())
    xx = 2.0 * uv.data_array[:, 0, 0].reshape(uv.Ntimes, uv.Nbls)
    flags = np.any(uv.flag_array[:, 0, :], axis=-1).reshape(uv.Ntimes, uv.Nbls)
    vi, wi = stokes_i(ms["vis"][:, :, 0].astype(complex), ms["weights"][:, :, 0])
    np.testing.assert_array_equal(wi == 0, flags)  # Stokes I is flagged where either hand is
    np.testing.assert_allclose(vi[~flags], (0.95 * xx)[~flags], rtol=0, atol=4 * F32 * np.abs(xx).max())
    # the same map, end to end
    maps = {}
    for name, pattern in (("h", scan["root"] / "uvh5" / "*.uvh5"), ("m", scan["ms"] / "*.ms")):
        run_workflow(_cfg(scan, tmp_path / name, str(pattern)), progress=False, log=lambda *a: None)
        maps[name] = healpy.read_map(str(tmp_path / name / "maps" / "map_40.000MHz.fits"))
    peak = np.max(np.abs(maps["h"]))
    assert peak > 0 and np.max(np.abs(maps["m"] - maps["h"])) <= 1e-5 * peak


def test_uvfits_per_integration_ingests_to_the_uvh5_store(scan, tmp_path):
    ref = _ingest(scan, tmp_path / "h", str(scan["root"] / "uvh5_12" / "*.uvh5"))
    fits = _ingest(scan, tmp_path / "f", str(scan["root"] / "uvfits_12" / "*.uvfits"))
    assert ref.attrs["ingest_file_info"][0]["phase"] == "drift"
    assert fits.attrs["ingest_file_info"][0]["phase"] == "phased"
    _same_store(ref, fits)


def test_ms_plan_reads_one_file_with_pyuvdata_the_rest_with_casacore_and_checks_each(scan, tmp_path):
    """The plan's casacore pass over many MS gives pyuvdata's plan, and refuses what pyuvdata's would."""
    from casacore.tables import table

    from mmflow.errors import InputError
    from mmflow.io import ingest
    from mmflow.io.ms_index import MSIndex

    d = tmp_path / "ms"
    d.mkdir()
    for p in sorted(scan["ms"].glob("*.ms"))[:5]:
        shutil.copytree(p, d / p.name)
    files = [str(p) for p in sorted(d.glob("*.ms"))]
    fast = ingest._metadata_indexed(files, None, "error", "ms")
    assert fast is not None and all(isinstance(m, MSIndex) for m in fast[0][1:])
    slow = ingest._metadata_pyuvdata(files, None, "error")
    assert fast[1] == slow[1] and fast[3] == slow[3]  # same files, same per-file info
    for a, b in zip(fast[0], slow[0]):
        np.testing.assert_array_equal(a.time_array, b.time_array)
        np.testing.assert_array_equal(a.ant_1_array, b.ant_1_array)
        np.testing.assert_array_equal(a.ant_2_array, b.ant_2_array)

    def refused(match, edit, name):
        bad = tmp_path / name
        shutil.copytree(d, bad)
        edit(str(bad / "int_0003.ms"))
        ingest.plan_ingest.cache_clear()
        with pytest.raises(InputError, match=match):
            ingest.plan_ingest(str(bad / "*.ms"), None, "error")

    def move_antenna(p):
        with table(p + "/ANTENNA", readonly=False, ack=False) as t:
            t.putcell("POSITION", 3, t.getcell("POSITION", 3) + np.array([0.0, 0.05, 0.0]))

    def uncalibrated(p):
        with table(p, readonly=False, ack=False) as t:
            t.putcolkeyword("DATA", "QuantumUnits", "uncalib")

    def duplicate_row(p):
        with table(p, readonly=False, ack=False) as t:
            t.putcell("ANTENNA2", 2, t.getcell("ANTENNA2", 1))

    refused(r"int_0003.ms.*antenna_positions.*antenna 3 is 0.050 m", move_antenna, "moved")
    refused(r"int_0003.ms.*vis_units.*'uncalib'", uncalibrated, "uncal")
    refused(r"int_0003.ms.*duplicated \(time, baseline\) rows: rows 1 and 2", duplicate_row, "dup")
    shutil.copytree(d / "int_0001.ms", d / "int_0001_copy.ms")
    ingest.plan_ingest.cache_clear()
    with pytest.raises(InputError, match=r"time_array.*also in"):
        ingest.plan_ingest(str(d / "*.ms"), None, "error")


@pytest.mark.parametrize("convention", ["keyword", "history"])
def test_direct_ms_read_equals_pyuvdata_read_and_unprojection(scan, tmp_path, convention):
    """The tasks' casacore reader gives what pyuvdata's read + unproject_phase gives, bit for bit
    (LSTs to 1e-9 rad: computed at the plan's site), whether the conjugation convention is in the
    main table's keyword or (keyword removed, as in files not written by pyuvdata) in HISTORY."""
    from casacore.tables import table

    from mmflow.io.readers import _CASACORE_LOCK, _read_pyuvdata
    from mmflow.io.ms_read import read_ms_direct

    src = sorted(scan["ms"].glob("*.ms"))[5]
    path = tmp_path / src.name
    shutil.copytree(src, path)
    if convention == "history":
        with table(str(path), readonly=False, ack=False) as t:
            t.removekeyword("pyuvdata_flip_conj")
    ref, info = _read_pyuvdata(path, None, None)
    assert info["phase"] == "phased"
    loc = scan["uv"].telescope.location
    site = (loc.lat.deg, loc.lon.deg, loc.height.to_value("m"))
    got = read_ms_direct(path, info["pol_numbers"], True, site, _CASACORE_LOCK)
    for name in ("time_jd", "ant1", "ant2", "vis", "flags", "freqs"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
    np.testing.assert_array_equal(got.nsample.astype(np.float32), ref.nsample.astype(np.float32))
    np.testing.assert_allclose(got.lst, ref.lst, rtol=0, atol=1e-9)
