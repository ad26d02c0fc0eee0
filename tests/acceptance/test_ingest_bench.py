"""The ingest benchmark runs and reports rates for the same files read by pyuvdata and ingested (no timing asserts)."""
import os

import pytest


def test_bench_ingest_quick_reports_rates_for_uvh5_and_ms():
    pytest.importorskip("casacore")
    from mmflow.bench.ingest import run

    shm = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
    out = run(quick=True, directory=shm)
    for key in ("uvh5_per_integration", "uvh5_one_file", "ms_per_integration"):
        r = out[key]
        assert r["files"] == (1 if key == "uvh5_one_file" else out["integrations"]) and r["mb"] > 0
        assert r["raw_files_per_s"] > 0 and r["ingest_files_per_s"] > 0
        # the ratio is computed from the unrounded times; both printed times are rounded to 1 ms
        lo = (r["raw_read_s"] - 5e-4) / (r["ingest_s"] + 5e-4)
        hi = (r["raw_read_s"] + 5e-4) / max(r["ingest_s"] - 5e-4, 1e-9)
        assert lo - 5e-4 <= r["ratio_to_raw"] <= hi + 5e-4
    assert not os.path.exists(out["directory"])  # the files are removed
