"""Record the normal and solve stages at a chosen Gram size, cheaply: few antennas, any lmax.

The normal and solve tasks' memory and time depend on the Gram blocks (``mmode.lmax``,
``transfer.m_block``, ``transfer.groups``) and on how full the blocks are, not on the array's size:
48 stands of the paper's layout (:func:`spread_stands`: 24 of its core and 24 of its outer stands,
evenly in radius) fill every block to ``lmax`` as the paper's 256 do, with 1,128 baselines instead of
32,896, so the transfer stage is seconds at lmax 1000 while the normal and solve tasks are those of the
paper's channel. (The first 16 core stands, the records' earlier choice, leave the Grams zero beyond
l ~ 150: their eigen-decompositions deflate, and solve ran 3.66x faster a task than the paper's
channel: docs/planning.md.) Used for the records ``mmflow/workflow/plan/records/gram-stages-l*.json``::

    python benchmarks/record_gram_stages.py RUN_DIR LMAX [override ...] > record.json

The run stops after solve (simulate, mmodes, transfer, normal, solve on local clusters of two
one-thread workers; no calibration, peeling or terrestrial filter); the record keeps normal and solve
only (the others' tasks are not those of any planned run's size). Normal and solve run on workers of
their own: a task's memory is measured as its worker's peak above the worker's resident memory when it
started, and workers that had run the simulation held ~110 MB of freed memory that the normal tasks at
lmax 500 reused (20 MB measured a task against the 129 MB they hold). A fresh worker's first task holds
the worker's one-time allocations instead (~60 MB more at lmax 500): the records mark normal's memory
``memory_superseded`` by hand, solve's holds. The SGEMM peak is measured before and after it.
"""
import json
import sys

import numpy as np

from mmflow.machine import gemm_gflops
from mmflow.telescope import ovro_lwa_layout
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.cluster import open_cluster
from mmflow.workflow.engine.runner import run_workflow
from mmflow.workflow.plan.fit import record

KEEP = ("normal", "solve")
#: the paper layout's core: stands within this radius of its centre (its outer stands lie beyond 157 m)
CORE_RADIUS_M = 150.0


def spread_stands(n_core=24, n_outer=24, preset="paper-2017"):
    """Names of ``n_core`` core and ``n_outer`` outer stands of ``preset``, each set evenly in radius."""
    lay = ovro_lwa_layout(preset)
    r = np.hypot(lay.enu[:, 0], lay.enu[:, 1])
    names = np.asarray(lay.names)
    chosen = []
    for part, n in ((r < CORE_RADIUS_M, n_core), (r >= CORE_RADIUS_M, n_outer)):
        idx = np.flatnonzero(part)
        idx = idx[np.argsort(r[idx], kind="stable")]
        chosen += list(idx[np.unique(np.linspace(0, len(idx) - 1, n).round().astype(int))])
    return [str(n) for n in names[sorted(chosen)]]


def main(run_dir, lmax, *extra):
    stands = "[" + ", ".join(spread_stands()) + "]"
    over = [f"telescope.stands={stands}", f"mmode.lmax={lmax}", "observation.freqs_mhz=[73.152]",
            "transfer.groups=2", "calibrate.enabled=false", "peel.enabled=false", "terrestrial.enabled=false",
            "cluster.kind=local", "cluster.n_workers=2", "cluster.threads_per_worker=1",
            "cluster.dashboard_address=:0", f"run.directory={run_dir}", *extra]
    cfg = load_config("workflows/paper-scale.yaml", over)
    before = gemm_gflops(np.float32)
    for only in (["simulate", "mmodes", "transfer"], list(KEEP)):  # KEEP's tasks on fresh workers
        with open_cluster(cfg, None, None, log=lambda *a: None) as client:
            run_workflow(cfg, client, only=only, progress=False, log=lambda *a: None)
    after = gemm_gflops(np.float32)
    rec = record(run_dir, sgemm_gflops=float(np.sqrt(before * after)),
                 note=f"{' '.join(['python benchmarks/record_gram_stages.py', run_dir, str(lmax), *extra])} (48 "
                      f"stands spread in radius, the Grams full to lmax); SGEMM {before:.1f} before / {after:.1f} "
                      f"after; only {', '.join(KEEP)} kept")
    rec["stages"] = {k: v for k, v in rec["stages"].items() if k in KEEP}
    json.dump(rec, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main(*sys.argv[1:])
