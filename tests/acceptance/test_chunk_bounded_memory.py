"""Issue 21: every time-chunked stage's task is bounded by its chunk, not by the data set.

The paper-scale workflow at reduced size (64 antennas, 2,080 baselines, the corrupted sky, the
simulate -> calibrate -> peel -> terrestrial chain) over one sidereal day with 256 and then 512
integrations (the calibration's solution interval kept at 64 integrations): the largest task of each
stage, read as the peak of the memory its arrays take (``tracemalloc``, started here: the runner
records ``traced_peak_gb`` per task, :func:`mmflow.workflow.engine.resources.reset_traced_peak`), grows by
less than 10 % when the integrations double; a task holding every integration would grow by ~100 %.
The traced peak, unlike a resident-set reading, does not move with the allocator's state; it does
count what a stage caches on its first call in a process (the calibrate task of a process's first run
read 0.108 GB, of a second 0.090 GB, at 256 or 512 integrations alike), so a short run warms the
process first and both readings are taken warm. (The m-mode corner turn holds every integration
of its baseline chunk by design: it is bounded by ``mmode.baseline_chunk``, and the plan says so.)
"""
import tracemalloc

from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.rundir import RunDir
from mmflow.workflow.engine.runner import run_workflow

STAGES = ("simulate", "calibrate", "peel", "terrestrial")
DAY_S = 86164.0905


def _task_peaks(tmp_path, n, lmax=100):
    tau = DAY_S / n
    cfg = load_config("workflows/paper-scale.yaml", [
        "telescope.max_antennas=64", f"observation.integration_s={tau:.7f}", f"calibrate.solint_s={64 * tau:.4f}",
        f"mmode.lmax={lmax}", "sky.diffuse=false", "cluster.kind=synchronous", f"run.directory={tmp_path / str(n)}"])
    run_workflow(cfg, only=STAGES, progress=False, log=lambda *a: None)
    run = RunDir(tmp_path / str(n))
    # every task's reading (a stage's records of its cycles carry none)
    return {st: max(i["traced_peak_gb"] for i in run.task_infos(st).values() if "traced_peak_gb" in i)
            for st in STAGES}


def test_task_memory_does_not_grow_with_the_integrations(tmp_path):
    tracemalloc.start()
    try:
        _task_peaks(tmp_path, 128, lmax=60)  # the first run's caches: neither reading below may hold them
        one, two = _task_peaks(tmp_path, 256), _task_peaks(tmp_path, 512)
    finally:
        tracemalloc.stop()
    print({st: (one[st], two[st]) for st in STAGES})
    for st in STAGES:
        assert one[st] > 0.01, (st, one[st])  # a working set of arrays, not a reading of nothing
        assert two[st] < 1.10 * one[st], (st, one[st], two[st])
