"""Record the normal and solve stages at a chosen Gram size, cheaply: few antennas, any lmax.

The normal and solve tasks' memory and time depend on the Gram blocks (``mmode.lmax``,
``transfer.m_block``, ``transfer.groups``), not on the array: with the first 16 stands of the
paper's layout the transfer stage is seconds at lmax 1000, and the normal and solve tasks are those
of the paper's channel. Used for the records ``mmflow/workflow/plan/records/gram-stages-l*.json``
(made when the Grams came to be stored as packed triangles; the earlier records' normal and solve
figures read them as squares and are superseded)::

    python benchmarks/record_gram_stages.py RUN_DIR LMAX [override ...] > record.json

The run stops after solve (simulate, mmodes, transfer, normal, solve on a local cluster of two
one-thread workers; no calibration: 16 core stands do not calibrate on the paper's sky model); the
record keeps normal and solve only (the others' tasks are not those of any planned run's size). The
SGEMM peak is measured before and after it.
"""
import json
import sys

import numpy as np

from mmflow.machine import gemm_gflops
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.cluster import open_cluster
from mmflow.workflow.engine.runner import run_workflow
from mmflow.workflow.plan.fit import record

KEEP = ("normal", "solve")


def main(run_dir, lmax, *extra):
    over = ["telescope.max_antennas=16", f"mmode.lmax={lmax}", "observation.freqs_mhz=[73.152]",
            "transfer.groups=2", "calibrate.enabled=false", "peel.enabled=false", "terrestrial.enabled=false",
            "cluster.kind=local", "cluster.n_workers=2", "cluster.threads_per_worker=1",
            "cluster.dashboard_address=:0", f"run.directory={run_dir}", *extra]
    cfg = load_config("workflows/paper-scale.yaml", over)
    before = gemm_gflops(np.float32)
    with open_cluster(cfg, None, None, log=lambda *a: None) as client:
        run_workflow(cfg, client, only=["simulate", "mmodes", "transfer", "normal", "solve"], progress=False,
                     log=lambda *a: None)
    after = gemm_gflops(np.float32)
    rec = record(run_dir, sgemm_gflops=float(np.sqrt(before * after)),
                 note=f"{' '.join(['python benchmarks/record_gram_stages.py', run_dir, str(lmax), *extra])} (the "
                      f"Grams packed); SGEMM {before:.1f} before / {after:.1f} after; only {', '.join(KEEP)} kept")
    rec["stages"] = {k: v for k, v in rec["stages"].items() if k in KEEP}
    json.dump(rec, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main(*sys.argv[1:])
