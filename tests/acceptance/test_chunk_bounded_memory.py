"""Issue 21: every time-chunked stage's task is bounded by its chunk, not by the data set.

The paper-scale workflow at reduced size (96 antennas, 4,656 baselines, the corrupted sky, the
calibrate -> peel -> terrestrial chain) run over one sidereal day with 512 and then 1,024
integrations (the calibration's solution interval kept at 64 integrations): the largest task of
simulate, calibrate, peel and terrestrial, measured as its peak resident memory above the process's
at its start (``mmflow.workflow.resources``), grows by less than 25 % (+ 50 MB) when the integrations
double (a task holding every integration would grow by ~100 %). Measured alone: simulate +4.6 %, the
others flat or smaller; in one process with the rest of the suite the same reading moved by up to
+22 % (one-off caches and the allocator's state of what ran before), so 10 % is not testable so.
(The m-mode corner turn holds every integration of its baseline chunk by design: it is bounded by
``mmode.baseline_chunk``, and the plan says so.)
"""

from mmflow.allocator import release_freed_memory
from mmflow.workflow.config import load_config
from mmflow.workflow.rundir import RunDir
from mmflow.workflow.runner import run_workflow

STAGES = ("simulate", "calibrate", "peel", "terrestrial")
DAY_S = 86164.0905


def _task_peaks(tmp_path, n):
    tau = DAY_S / n
    cfg = load_config("workflows/paper-scale.yaml", [
        "telescope.max_antennas=96", f"observation.integration_s={tau:.7f}", f"calibrate.solint_s={64 * tau:.4f}",
        "mmode.lmax=200", "sky.diffuse=false", "cluster.kind=synchronous", f"run.directory={tmp_path / str(n)}"])
    release_freed_memory()  # the previous run's freed memory out of the readings
    run_workflow(cfg, only=STAGES, progress=False, log=lambda *a: None)
    run = RunDir(tmp_path / str(n))
    out = {}
    for st in STAGES:
        infos = run.task_infos(st).values()
        grown = [i["peak_rss_gb"] - i["rss_start_gb"] for i in infos if i.get("peak_rss_gb") is not None]
        out[st] = max(grown)
    return out


def test_task_memory_does_not_grow_with_the_integrations(tmp_path):
    one, two = _task_peaks(tmp_path, 512), _task_peaks(tmp_path, 1024)
    print({st: (round(one[st], 3), round(two[st], 3)) for st in STAGES})
    for st in STAGES:
        assert one[st] > 0.05, (st, one[st])  # a working set well above the readings' noise
        assert two[st] < 1.25 * one[st] + 0.05, (st, one[st], two[st])  # readings move by ~+-0.03 GB
