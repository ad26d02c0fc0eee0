"""``mmflow bench paper``: the paper's channel end to end (``workflows/paper-scale.yaml``), measured.

Runs the whole workflow on the configured cluster (the default local one) in a new run directory
and prints, per stage, what the run recorded in its ``summary.json`` (``wall_s``, ``tasks``,
``worker_peak_rss_gb``, ``driver_peak_rss_gb``, ``bytes_written``) beside what ``mmflow plan``
predicted for it, with the SGEMM and DGEMM peaks measured before and after the run (this
machine's BLAS peak swings ~2x: a rate means little without the peak beside it).

By default the telescope's files come first, as issue 21 asks: the simulate stage alone writes the
corrupted drift scan as UVH5 files (``observation.raw_files: uvh5``, one per time chunk; its time is
``telescope_s``, not part of the run's), and the measured run reads them with ``source: ingest``, so
the real input path carries the load. ``--paper-source simulate`` runs the workflow as it is
(simulate straight into ``vis.zarr``).

``--quick`` runs the reduced scale of the issue's tests (64 antennas, 1/8 of the integrations
spread over the day, lmax 200); ``--scale`` picks another (``full`` is the paper's channel).
"""
from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from mmflow.io.raw_files import RAW_DIR
from mmflow.machine import gemm_gflops, machine
from mmflow.workflow.engine.cluster import open_cluster
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.plan.planner import plan
from mmflow.workflow.engine.runner import run_workflow

WORKFLOW = os.path.join(os.path.dirname(__file__), "..", "..", "workflows", "paper-scale.yaml")
#: overrides of each scale: the reduced runs keep the whole sidereal day (fewer, longer integrations)
SCALES = {
    "full": [],
    "reduced": ["telescope.max_antennas=64", "observation.integration_s=104.063", "mmode.lmax=200"],
    "small": ["telescope.max_antennas=32", "observation.integration_s=208.126", "mmode.lmax=100"],
}


def run(what="paper", quick=False, scale=None, overrides=(), directory=None, source="ingest"):
    scale = scale or ("reduced" if quick else "full")
    res = {"machine": machine(), "scale": scale, "source": source, "overrides": SCALES[scale] + list(overrides),
           "sgemm_gflops_before": gemm_gflops(np.float32), "dgemm_gflops_before": gemm_gflops(np.float64)}
    with tempfile.TemporaryDirectory(prefix="mmflow-bench-paper-", dir=directory) as root:
        if source == "ingest":  # the telescope writes its files first
            res["telescope_s"], res["raw_files_gb"], files = write_raw_files(res["overrides"], f"{root}/telescope")
            res["overrides"] += ["source=ingest", f"input.path={files}"]
        cfg = load_config(WORKFLOW, res["overrides"] + [f"run.directory={root}/run"])
        predicted = {e["stage"]: e for e in plan(cfg, peak_gflops=res["sgemm_gflops_before"])["stages"]}
        t0 = time.perf_counter()
        with open_cluster(cfg, log=lambda *a: None) as client:
            summaries = run_workflow(cfg, client, progress=False, log=lambda *a: None)
        res["wall_s"] = round(time.perf_counter() - t0, 1)
        res["stages"] = {name: {k: s.get(k) for k in ("wall_s", "tasks", "worker_peak_rss_gb",
                                                        "driver_peak_rss_gb", "bytes_written")}
                         | {"predicted_s": round(predicted[name]["seconds"], 1),
                            "predicted_task_gb": round(predicted[name]["task_bytes"] / 1e9, 3),
                            "predicted_store_gb": round(predicted[name]["store_bytes"] / 1e9, 3)}
                         for name, s in summaries.items() if name in predicted}
        table1 = os.path.join(root, "run", "maps", "table1.json")
        if os.path.exists(table1):
            with open(table1) as fh:
                res["table1"] = json.load(fh)
    res["sgemm_gflops_after"] = gemm_gflops(np.float32)
    res["dgemm_gflops_after"] = gemm_gflops(np.float64)
    return res


def write_raw_files(overrides, directory):
    """The simulate stage alone with ``observation.raw_files: uvh5`` in ``directory``: the telescope's
    UVH5 files. Returns (seconds, GB of files, their glob)."""
    cfg = load_config(WORKFLOW, list(overrides) + ["observation.raw_files=uvh5", f"run.directory={directory}"])
    t0 = time.perf_counter()
    with open_cluster(cfg, log=lambda *a: None) as client:
        run_workflow(cfg, client, only=["simulate"], progress=False, log=lambda *a: None)
    raw = Path(directory) / RAW_DIR
    size = sum(f.stat().st_size for f in raw.glob("*.uvh5"))
    return round(time.perf_counter() - t0, 1), round(size / 1e9, 3), str(raw / "*.uvh5")
