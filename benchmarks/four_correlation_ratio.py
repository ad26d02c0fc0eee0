"""The four correlations' time against Stokes I's, stage by stage, on the paper's array (JSON on stdout).

Runs the data stages (simulate, calibrate, peel, terrestrial) and the m-modes of ``workflows/paper-scale.yaml`` twice in
fresh run directories under ``ROOT``: with ``imaging.stokes=[I]`` and with ``[I, Q, U, V]`` (the four
correlations through the E-field beam, peel and terrestrial on xy and yx too), the same short-dipole beam,
no diffuse sky, ``N_INT`` integrations (whole time chunks; the m-modes of that part of the day over the whole
day's bins, without prior passes), one synchronous process, and any further ``key=value`` overrides (e.g.
``telescope.max_antennas=64``: fewer baselines, the same work per baseline). Prints each stage's
tasks' seconds (summed) in both and their ratio, beside this machine's SGEMM peak measured before and after.
The ratios are the ``FOUR_CORRELATION_TIME`` constants of the stages' cost models
(``mmflow/workflow/stages/*/cost.py``); docs/stokes.md gives the run they came from.

Usage: ``python benchmarks/four_correlation_ratio.py ROOT [N_INT [KEY=VALUE ...]]`` (ROOT must not exist; 512 by
default).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np

from mmflow.machine import gemm_gflops
from mmflow.workflow.engine.rundir import RunDir

STAGES = ("simulate", "calibrate", "peel", "terrestrial", "mmodes")
COMMON = ["workflows/paper-scale.yaml", "beam={type: short_dipole, horizon_taper: 3}", "sky.diffuse=false",
          "mmode.min_coverage=0.05", "mmode.prior_passes=0", "--cluster", "synchronous", "--no-progress"]
KINDS = {"I": "imaging.stokes=[I]", "IQUV": "imaging.stokes=[I, Q, U, V]"}


def task_seconds(run_dir, stage):
    """The seconds of each finished task of ``stage`` in ``run_dir`` (their completion markers)."""
    return [i["seconds"] for i in RunDir(run_dir).task_infos(stage).values() if "seconds" in i]


def main(root, n_int=512, *extra):
    os.makedirs(root)
    peak_before = gemm_gflops(np.float32)
    result = {"command": " ".join(["python benchmarks/four_correlation_ratio.py", root, str(n_int), *extra]),
              "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "n_integrations": n_int,
              "sgemm_gflops_before": round(peak_before, 1), "stages": {}}
    seconds = {}
    for kind, stokes in KINDS.items():
        run_dir = os.path.join(root, kind)
        for stage in STAGES:
            subprocess.run([sys.executable, "-m", "mmflow.cli", stage, *COMMON, stokes, *extra,
                            f"observation.n_integrations={n_int}", f"run.directory={run_dir}"],
                           check=True, stdout=subprocess.DEVNULL)
            seconds[kind, stage] = task_seconds(run_dir, stage)
    result["sgemm_gflops_after"] = round(gemm_gflops(np.float32), 1)
    for stage in STAGES:
        i, four = sum(seconds["I", stage]), sum(seconds["IQUV", stage])
        result["stages"][stage] = {"tasks": len(seconds["I", stage]), "task_s_I": round(i, 2),
                                   "task_s_IQUV": round(four, 2), "ratio": round(four / i, 2)}
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main(sys.argv[1], *(int(a) for a in sys.argv[2:3]), *sys.argv[3:])
