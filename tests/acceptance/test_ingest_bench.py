"""The ingest benchmark runs and reports rates for the same files read by pyuvdata and ingested (no timing asserts);
its raw OVRO-LWA case ingests the values pyuvdata reads."""
import os
import shutil
from pathlib import Path

import pytest


def _shm():
    """tmpfs where there is one: casacore syncs every table it writes."""
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None


def test_bench_ingest_quick_reports_rates_for_uvh5_and_ms():
    pytest.importorskip("casacore")
    from mmflow.bench.ingest import run

    out = run(quick=True, directory=_shm())
    for key in ("uvh5_per_integration", "uvh5_one_file", "ms_per_integration"):
        r = out[key]
        assert r["files"] == (1 if key == "uvh5_one_file" else out["integrations"]) and r["mb"] > 0
        assert r["raw_files_per_s"] > 0 and r["ingest_files_per_s"] > 0
        # the ratio is computed from the unrounded times; both printed times are rounded to 1 ms
        lo = (r["raw_read_s"] - 5e-4) / (r["ingest_s"] + 5e-4)
        hi = (r["raw_read_s"] + 5e-4) / max(r["ingest_s"] - 5e-4, 1e-9)
        assert lo - 5e-4 <= r["ratio_to_raw"] <= hi + 5e-4
    assert not os.path.exists(out["directory"])  # the files are removed


@pytest.mark.filterwarnings("ignore:select on read keyword set")
def test_bench_ingest_raw_quick_reports_both_cases_and_ingests_what_pyuvdata_selects():
    """The raw OVRO-LWA case (3 MeasurementSets of 6 antennas): both cases report pyuvdata's full and
    selected reads and ingest, wall and CPU; the files are the telescope's layout; the stores kept by
    the bench hold pyuvdata's own read of the same channel (xx yy and xy yx, unprojected), and of the
    4-channel average (``frequency_average``)."""
    pytest.importorskip("casacore")
    import numpy as np
    import zarr
    from pyuvdata import UVData

    from mmflow.bench.ingest import RAW_CASES, run
    from tests.rawfile_helpers import pyuvdata_reference

    out = run(quick=True, raw=True, directory=_shm(), keep=True)
    root = Path(out["directory"])
    try:
        assert (out["n_freq"], out["n_pol"], out["vis_units"], out["phase_frame"]) == (109, 4, "uncalib", "fk5")
        files = sorted((root / "ms").glob("*.ms"))
        assert len(files) == out["integrations"]
        meta = UVData.from_file(str(files[-1]), read_data=False)
        (cat,) = meta.phase_center_catalog.values()
        assert meta.Ntimes == 1 and meta.Nfreqs == 109 and meta.telescope.name == "OVRO_MMA"
        assert (cat["cat_frame"], cat["cat_epoch"]) == ("fk5", 2000.0)
        for name, n_avg in RAW_CASES:
            r = out[name]
            assert r["files"] == len(files) and r["mb"] > 0 and len(r["file_channels"]) == n_avg
            for part in ("raw_read", "raw_select_read", "ingest", "ingest_plan", "ingest_tasks"):
                assert r[f"{part}_s"] > 0 and r[f"{part}_cpu_s"] >= 0
            for part in ("raw", "raw_select", "ingest"):
                assert r[f"{part}_files_per_s"] > 0 and r[f"{part}_mb_per_s"] > 0
            assert r["ratio_to_raw"] > 0 and r["ratio_to_raw_select"] > 0
            g = zarr.open_group(str(root / f"{name}.run" / "vis.zarr"), mode="r")
            for pols, vis, wts in (((-5, -6), "vis", "weights"), ((-7, -8), "vis_cross", "weights_cross")):
                uv = UVData.from_file([str(f) for f in files], freq_chans=r["file_channels"])
                ref = pyuvdata_reference(uv, (lambda u: u.frequency_average(n_avg)) if n_avg > 1 else None, pols)
                _, _, pairs, v, w = ref
                np.testing.assert_allclose(g["freqs_hz"][:], out["channel_mhz"] * 1e6 + (n_avg > 1) * 12e3)
                np.testing.assert_array_equal(g["pairs"][:], pairs)
                np.testing.assert_allclose(g[wts][:], w, rtol=1e-6, atol=0)
                np.testing.assert_allclose(g[vis][:], v, rtol=0, atol=4 * np.finfo(np.float32).eps * np.abs(v).max())
    finally:
        shutil.rmtree(root)
