"""The mmodes stage's planned task memory against its traced peak, over configurations (JSON on stdout).

Each configuration is ``workflows/paper-scale.yaml`` reduced as ``tests/acceptance/test_plan_traced.py`` reduces it
(64 antennas, lmax 200, 512 integrations over the sidereal day, the calibration's interval 64 integrations, no
diffuse sky, synchronous) with the overrides below: Stokes I or the four correlations (``imaging.stokes=[I, Q, U,
V]`` through short dipoles), peel and terrestrial on or off (off, the read of a block is small and the fits are
the peak; on, the peel's correction on read is), more integrations, other lmax, more channels, larger baseline
chunks. Each runs simulate -> mmodes in a fresh process under ``tracemalloc`` in its own run directory under
ROOT and prints the largest mmodes task's traced peak beside the cost model's working set ``W``
(``mmflow/workflow/stages/mmodes/cost.py``) and their ratio.

Usage: ``python benchmarks/mmode_task_memory.py ROOT`` (ROOT must not exist; ~4 min on 2 cores).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

DAY_S = 86164.0905
IQUV = ["imaging.stokes=[I, Q, U, V]", "beam={type: short_dipole, horizon_taper: 3}"]
NO_PEEL = ["peel.enabled=false", "terrestrial.enabled=false"]
#: name -> (integrations, overrides)
CASES = {
    "I": (512, NO_PEEL),
    "IQUV": (512, IQUV + NO_PEEL),
    "I peel": (512, []),
    "IQUV peel": (512, IQUV),
    "I 1024 integrations lmax 120": (1024, NO_PEEL + ["mmode.lmax=120"]),
    "I lmax 60": (512, NO_PEEL + ["mmode.lmax=60"]),
    "IQUV 2 channels": (512, IQUV + NO_PEEL + ["observation.freqs_mhz=[40.0, 50.0]"]),
    "I 4 channels": (512, NO_PEEL + ["observation.freqs_mhz=[40.0, 50.0, 60.0, 70.0]"]),
    "I baseline_chunk 512": (512, NO_PEEL + ["mmode.baseline_chunk=512"]),
}
STAGES = ["simulate", "calibrate", "models", "peel", "terrestrial", "mmodes"]

CHILD = """
import json, sys, tracemalloc
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.rundir import RunDir
from mmflow.workflow.engine.runner import run_workflow
from mmflow.workflow.plan.planner import geometry, stage_work
cfg = load_config("workflows/paper-scale.yaml", json.loads(sys.argv[1]))
tracemalloc.start()
run_workflow(cfg, only=json.loads(sys.argv[2]), progress=False, log=lambda *a: None)
tracemalloc.stop()
traced = max(i["traced_peak_bytes"] for i in RunDir(cfg.run.directory).task_infos("mmodes").values())
print("RESULT=" + json.dumps({"traced": traced, "W": stage_work("mmodes", geometry(cfg), cfg).working_set_bytes}))
"""


def overrides(run_dir, n_time, extra):
    tau = DAY_S / n_time
    return ["telescope.max_antennas=64", f"observation.integration_s={tau:.7f}",
            f"calibrate.solint_s={64 * tau:.4f}", "mmode.lmax=200", "sky.diffuse=false", "cluster.kind=synchronous",
            f"run.directory={run_dir}", *extra]


def main(root):
    root = Path(root)
    root.mkdir(parents=True)
    rows = {}
    for i, (name, (n_time, extra)) in enumerate(CASES.items()):
        out = subprocess.run([sys.executable, "-c", CHILD, json.dumps(overrides(root / f"r{i}", n_time, extra)),
                              json.dumps(STAGES)], capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.split("RESULT=", 1)[1])
        rows[name] = {"traced_mb": round(r["traced"] / 1e6, 2), "W_mb": round(r["W"] / 1e6, 2),
                      "W/traced": round(r["W"] / r["traced"], 3)}
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main(sys.argv[1])
