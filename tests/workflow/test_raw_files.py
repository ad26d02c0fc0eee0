"""``observation.raw_files: uvh5``: the simulate stage writes its drift scan as the UVH5 files a
telescope writes, and a run with ``source: ingest`` reads them back to the same visibilities.

Independent of the writer: the files are read with pyuvdata itself, and through ingest's own plan
(LSTs recomputed from the files' UTC times, the flux convention from the file's ``pol_convention``).
"""
import numpy as np
import pytest
import zarr

from mmflow.cli import main
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow
from tests.workflow_helpers import refused_problem

QUIET = dict(progress=False, log=lambda *a: None)
DEMO = "workflows/demo-calibrate.yaml"
#: two channels, 600 integrations of 13 s in 3 time chunks of 256 (the last one short), 10 stands
SMALL = ["telescope.max_antennas=10", "observation.freqs_mhz=[62.688, 73.152]", "observation.n_integrations=600",
         "mmode.min_coverage=0", "cluster.kind=synchronous", "observation.raw_files=uvh5"]


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("raw")
    cfg = load_config(DEMO, SMALL + [f"run.directory={d / 'sim'}"])
    run_workflow(cfg, only=["simulate"], **QUIET)
    return d


def test_one_file_per_time_chunk_with_every_baseline_channel_and_hand(sim):
    from pyuvdata import UVData

    files = sorted((sim / "sim" / "raw").glob("*.uvh5"))
    assert [f.name for f in files] == ["t000000.uvh5", "t000256.uvh5", "t000512.uvh5"]
    v = zarr.open_group(str(sim / "sim" / "vis.zarr"), mode="r")
    pairs, vis = v["pairs"][:], v["vis"][:]
    uv = UVData.from_file(str(files[1]))
    assert uv.Ntimes == 256 and uv.Nbls == len(pairs) and uv.Nfreqs == 2
    assert sorted(uv.get_pols()) == ["xx", "yy"] and uv.pol_convention == "avg" and uv.vis_units == "Jy"
    np.testing.assert_allclose(uv.freq_array.ravel(), [62.688e6, 73.152e6])
    i, j = map(int, pairs[7])
    assert i != j
    np.testing.assert_array_equal(uv.get_data(i, j, "yy"), vis[256:512, 7, :, 1])  # complex64 written exactly
    assert not uv.flag_array.any()
    # the written markers name the files: --force would remove exactly those, verify checks them
    assert main(["verify", str(sim / "sim")]) == 0


def test_ingest_reads_back_the_simulated_visibilities(sim):
    d = sim
    cfg = load_config(DEMO, SMALL + ["source=ingest", f"input.path={d / 'sim' / 'raw'}/*.uvh5",
                                     f"run.directory={d / 'ing'}"])
    run_workflow(cfg, only=["ingest"], **QUIET)
    a = zarr.open_group(str(d / "sim" / "vis.zarr"), mode="r")
    b = zarr.open_group(str(d / "ing" / "vis.zarr"), mode="r")
    assert b.attrs["pols"] == ["xx", "yy"] and b.attrs["pol_convention"] == "avg" and b.attrs["pol_factor"] == 1
    assert np.array_equal(a["pairs"][:], b["pairs"][:]) and np.array_equal(a["freqs_hz"][:], b["freqs_hz"][:])
    va, vb = a["vis"][:], b["vis"][:]
    autos = a["pairs"][:, 0] == a["pairs"][:, 1]
    assert np.array_equal(va[:, ~autos], vb[:, ~autos])  # bit for bit
    assert np.array_equal(va[:, autos].real, vb[:, autos].real) and not vb[:, autos].imag.any()
    assert np.array_equal(b["weights"][:], np.ones(vb.shape, np.float32))
    # the LSTs recomputed from the files' UTC times are the simulated ones
    assert np.abs(np.angle(np.exp(1j * (a["lst"][:] - b["lst"][:])))).max() < 1e-7
    np.testing.assert_allclose(b["antenna_enu"][:], a["antenna_enu"][:], atol=1e-3)


def test_a_full_stokes_simulation_writes_the_four_correlations(tmp_path):
    """Through the E-field beam: XX, YY, XY, YX in each file; ingest carries the cross hands as simulated."""
    base = ["telescope.max_antennas=6", "observation.freqs_mhz=[73.152]", "observation.n_integrations=300",
            "mmode.min_coverage=0", "cluster.kind=synchronous", "observation.raw_files=uvh5",
            "imaging.stokes=[I, Q, U, V]", "beam={type: short_dipole}", "corrupt.enabled=false",
            "calibrate.enabled=false", "peel.enabled=false", "terrestrial.enabled=false"]
    run_workflow(load_config(DEMO, base + [f"run.directory={tmp_path / 'sim'}"]), only=["simulate"], **QUIET)
    from pyuvdata import UVData

    uv = UVData.from_file(str(tmp_path / "sim" / "raw" / "t000256.uvh5"))
    assert sorted(uv.get_pols()) == ["xx", "xy", "yx", "yy"] and uv.Ntimes == 44
    cfg = load_config(DEMO, base + ["source=ingest", f"input.path={tmp_path / 'sim' / 'raw'}/*.uvh5",
                                    f"run.directory={tmp_path / 'ing'}"])
    run_workflow(cfg, only=["ingest"], **QUIET)
    a = zarr.open_group(str(tmp_path / "sim" / "vis.zarr"), mode="r")
    b = zarr.open_group(str(tmp_path / "ing" / "vis.zarr"), mode="r")
    cross = a["pairs"][:, 0] != a["pairs"][:, 1]
    assert b.attrs["cross_pols"] == ["xy", "yx"]
    assert np.array_equal(a["vis_cross"][:, cross], b["vis_cross"][:, cross])
    assert np.array_equal(a["vis"][:, cross], b["vis"][:, cross])
    autos = ~cross  # an antenna's XY is complex (only the parallel hands' autos are real)
    assert np.array_equal(a["vis_cross"][:, autos], b["vis_cross"][:, autos]) and b["vis_cross"][:, autos].imag.any()


def test_a_clean_stokes_i_simulation_cannot_write_raw_files():
    (_, _, problem, fix), _ = refused_problem(["observation.raw_files=uvh5"], "observation.raw_files",
                                              path="workflows/demo.yaml")
    assert "XX and YY" in problem and "corrupt.enabled" in fix
