"""Benchmark: ingest of one file per integration against pyuvdata's own read rate, same files, same run.

Writes ``n`` single-integration UVH5 files and ``n`` single-integration MeasurementSets (phased to
the zenith of their integration, as the OVRO-LWA writes them; needs python-casacore) of a random
drift scan, plus one UVH5 holding all ``n`` integrations, and reports for each set:

* ``raw``: a serial loop of ``pyuvdata.UVData.read`` over the files (default arguments; the best of
  two passes, the files already in the page cache), files/s and MB/s;
* ``ingest``: mmflow's plan (metadata of every file, checks) plus the ingest tasks writing
  ``vis.zarr`` (run one after another in this process, as ``cluster.kind=synchronous`` runs them),
  files/s and MB/s, and ``ratio_to_raw`` = ingest rate / raw rate (goal >= 0.8);
* the split between plan and tasks.

MB are the files' sizes on disk. ``run(quick=True)`` is small enough for a test.
``mmflow bench ingest [--quick]`` prints the JSON (``MMFLOW_BENCH_DIR=/dev/shm`` for MS: casacore writes slowly).
"""
from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mmflow.conventions import SIDEREAL_DAY_S


def _scan(n_ant, n_freq, n_time, seed=0):
    """A random drift scan (two linear polarisations) on a random 100 m layout at the OVRO-LWA site."""
    from astropy import units as u
    from astropy.coordinates import EarthLocation
    from pyuvdata import Telescope, UVData
    from pyuvdata.utils import ECEF_from_ENU

    rng = np.random.default_rng(seed)
    loc = EarthLocation.from_geodetic(-118.2817 * u.deg, 37.2398 * u.deg, 1183.0 * u.m)
    enu = np.column_stack([rng.uniform(-50, 50, n_ant), rng.uniform(-50, 50, n_ant), np.zeros(n_ant)])
    ecef = ECEF_from_ENU(enu, center_loc=loc) - np.array([loc.x.to_value("m"), loc.y.to_value("m"),
                                                            loc.z.to_value("m")])
    tel = Telescope.new("bench", loc, antenna_positions=ecef, antenna_names=[f"A{k}" for k in range(n_ant)],
                        antenna_numbers=list(range(n_ant)), instrument="bench", mount_type="fixed")
    antpairs = [(i, j) for i in range(n_ant) for j in range(i, n_ant)]
    dt = 13.0
    times = 2460000.5 + np.arange(n_time) * dt / 86400.0
    shape = (n_time * len(antpairs), n_freq, 2)
    data = (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(np.complex64)
    freqs = 40e6 + 24e3 * np.arange(n_freq)
    uv = UVData.new(freq_array=freqs, polarization_array=np.array([-5, -6]), times=times, telescope=tel,
                    antpairs=antpairs, do_blt_outer=True, data_array=data.astype(np.complex128),
                    integration_time=dt, channel_width=24e3, vis_units="Jy", time_axis_faster_than_bls=False)
    uv._fix_autos()
    uv.pol_convention = "avg"  # XX = I, as CASA writes (docs/conventions.md)
    return uv


def _write(uv, directory, fmt):
    from mmflow.io.export import write_per_integration

    directory.mkdir(parents=True)
    return write_per_integration(uv, directory, fmt)


def _size_mb(paths):
    total = 0
    for p in paths:
        p = Path(p)
        total += sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) if p.is_dir() else p.stat().st_size
    return total / 1e6


def _raw_read_s(paths):
    from pyuvdata import UVData

    best = np.inf
    for _ in range(2):
        t0 = time.perf_counter()
        for p in paths:
            UVData().read(str(p))
        best = min(best, time.perf_counter() - t0)
    return best


def _ingest_s(pattern, store):
    """mmflow's ingest as the stage runs it: plan, store, tasks over time chunks."""
    from types import SimpleNamespace

    from mmflow.io import ingest
    from mmflow.io.run_stores import vis_store
    from mmflow.threads import n_threads
    from mmflow.workflow.chunking import TIME_CHUNK
    from mmflow.workflow.data_stage import layout_attrs

    cfg = SimpleNamespace(input=SimpleNamespace(path=pattern, format=None, on_bad_file="error", conjugate=False,
                                                nonfinite="error"))
    ingest._plan.cache_clear()
    n_threads()  # its first call imports distributed (docs/performance.md): a worker has it loaded already
    t0 = time.perf_counter()
    plan = ingest.plan_ingest(cfg)
    spec = vis_store(plan.n_time, plan.pairs, plan.freqs_hz, plan.layout.enu,
                     {**layout_attrs(plan.layout), "source": "ingest", "epoch_jd": plan.epoch_jd, "files": plan.files,
                      "skipped_files": plan.skipped, "integration_s": plan.integration_s, "pols": plan.pols},
                     TIME_CHUNK, 256)
    g = spec.create(store)  # the stage's own store declaration
    ingest.write_plan(g, plan)
    store = store / spec.path
    t1 = time.perf_counter()
    for r0 in range(0, plan.n_time, TIME_CHUNK):
        ingest.ingest_time_chunk(cfg, store, r0, r0 + TIME_CHUNK)
    t2 = time.perf_counter()
    shutil.rmtree(store.parent)
    return t1 - t0, t2 - t1


def _measure(paths, pattern, store):
    mb = _size_mb(paths)
    n = len(paths)
    raw = _raw_read_s(paths)
    plan_s, tasks_s = _ingest_s(pattern, store)
    ing = plan_s + tasks_s
    return {"files": n, "mb": round(mb, 2), "raw_read_s": round(raw, 3), "raw_files_per_s": round(n / raw, 1),
            "raw_mb_per_s": round(mb / raw, 1), "ingest_s": round(ing, 3), "ingest_plan_s": round(plan_s, 3),
            "ingest_tasks_s": round(tasks_s, 3), "ingest_files_per_s": round(n / ing, 1),
            "ingest_mb_per_s": round(mb / ing, 1), "ratio_to_raw": round(raw / ing, 3)}


def run(what="ingest", quick=False, directory=None):
    """Measure; returns a dict (see the module docstring). ``directory``: where to write the files
    (default: the system temporary directory; ``MMFLOW_BENCH_DIR`` overrides)."""
    import mmflow  # noqa: F401  (offline astropy)
    from mmflow.threads import n_threads

    n_ant, n_freq, n_time = (16, 8, 24) if quick else (64, 32, 256)
    uv = _scan(n_ant, n_freq, n_time)
    root = Path(tempfile.mkdtemp(prefix="mmflow-bench-ingest-",
                                 dir=directory or os.environ.get("MMFLOW_BENCH_DIR")))
    out = {"n_ant": n_ant, "n_baselines": int(uv.Nbls), "n_freq": n_freq, "n_pol": 2, "integrations": n_time,
           "threads": n_threads(), "directory": str(root)}
    try:
        paths = _write(uv, root / "uvh5", "uvh5")
        out["uvh5_per_integration"] = _measure(paths, str(root / "uvh5" / "*.uvh5"), root / "s1.zarr")
        one = root / "one" / "all.uvh5"
        one.parent.mkdir()
        uv.write_uvh5(str(one))
        out["uvh5_one_file"] = _measure([one], str(one), root / "s2.zarr")
        out["per_integration_over_one_file_ingest_time"] = round(
            out["uvh5_per_integration"]["ingest_s"] / out["uvh5_one_file"]["ingest_s"], 2)
        try:
            import casacore  # noqa: F401
        except ImportError:
            out["ms_per_integration"] = "skipped: python-casacore not installed"
        else:
            paths = _write(uv, root / "ms", "ms")
            out["ms_per_integration"] = _measure(paths, str(root / "ms" / "*.ms"), root / "s3.zarr")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return out


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
