"""``mmflow bench workflow``: what the workflow's own bookkeeping costs, measured on real runs.

For each case a whole workflow runs (in process, synchronous scheduler) in a temporary
directory; per stage the JSON gives the wall time, the time inside tasks, the time spent on
chunk checksums (XXH3 checksum of every written and read chunk) and on the non-finite guard, and
their fractions of the stage. The run-directory lock is taken once per run (one ``flock``).
Cases: ``demo`` (the demo's workflow, one channel) and, without ``--quick``, ``lmax1000``
(16 paper-2017 stands, 136 baselines all at lmax 1000, float32, one sidereal day at 73 MHz;
stages up to the normal equations).
"""
from __future__ import annotations

import os
import tempfile
import time

import numpy as np

from mmflow.io.stores import checksum
from mmflow.machine import gemm_gflops, machine
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow

CASES = {
    "demo": ["observation.freqs_mhz=[40.0]"],
    "lmax1000": ["telescope.preset=paper-2017", "telescope.radius_m=null", "telescope.max_antennas=16",
                 "observation.freqs_mhz=[73.152]", "sky.diffuse=false", "sky.sources=[Cyg A, Cas A]",
                 "sky.noise=false", "mmode.lmax=1000", "mmode.baseline_chunk=256", "transfer.dtype=float32",
                 "transfer.per_baseline_lmax=false", "transfer.baseline_chunk=64", "transfer.groups=2",
                 "transfer.noise_weighting=false", "imaging.lcurve=false", "products.nside=512"],
}


# the lmax-1000 case stops after the reduction: its solve is dominated by eigvalsh (issue 12)
ONLY = {"lmax1000": ["simulate", "mmodes", "transfer", "normal"]}


def run_case(name, root):
    demo = os.path.join(os.path.dirname(__file__), "..", "..", "workflows", "demo.yaml")
    cfg = load_config(demo, CASES[name] + ["cluster.kind=synchronous", f"run.directory={root}/{name}"])
    t0 = time.perf_counter()
    summaries = run_workflow(cfg, only=ONLY.get(name), progress=False, log=lambda *a: None)
    wall = time.perf_counter() - t0
    stages = {}
    for st, s in summaries.items():
        book = s["checksum_s"] + s["guard_s"]
        stages[st] = {"wall_s": s["wall_s"], "task_s": s["task_s"], "checksum_s": s["checksum_s"],
                      "guard_s": s["guard_s"], "bytes_written": s["bytes_written"],
                      "bookkeeping_fraction_of_stage": book / s["wall_s"] if s["wall_s"] else None}
    total_book = sum(v["checksum_s"] + v["guard_s"] for v in stages.values())
    return {"case": name, "overrides": CASES[name], "wall_s": wall, "stages": stages,
            "bookkeeping_s": total_book, "bookkeeping_fraction": total_book / wall}


def checksum_rate(n_bytes=256 << 20):
    """Chunk-checksum throughput of this machine (GB/s, in memory)."""
    data = np.frombuffer(np.random.default_rng(0).bytes(n_bytes), np.uint8)
    t0 = time.perf_counter()
    checksum(data)
    return n_bytes / (time.perf_counter() - t0) / 1e9


def run(what="workflow", quick=False):
    res = {"machine": machine(), "sgemm_gflops": gemm_gflops(np.float32), "checksum_gb_per_s": checksum_rate()}
    with tempfile.TemporaryDirectory(prefix="mmflow-bench-") as root:
        res["cases"] = [run_case(n, root) for n in (["demo"] if quick else ["demo", "lmax1000"])]
    return res
