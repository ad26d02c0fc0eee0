"""Fit the plan's per-stage constants to measured runs (``mmflow plan --fit RUN_DIR ...``).

Every finished task records in its marker the seconds it took, the resident memory of its worker
when it started (``rss_start_gb``) and the worker's peak while it ran (``peak_rss_gb``,
:mod:`mmflow.workflow.resources`). For each stage and run this gives one sample: the largest task's
memory above its worker's baseline, ``max(peak - start)``, and the mean seconds per task. Against
the stage's modelled working set ``W`` and work units ``U`` (:func:`mmflow.workflow.plan.stage_work`
of the run's own configuration) the constants of

    memory = a W + b,     seconds = c U + d

are fitted over the runs (:func:`fit_memory`): where the runs' working sets span at least
:data:`SLOPE_SPAN` (a paper-scale run beside small ones), ``a, b`` a least-squares line, ``a >= 1``
(a task holds at least its working set; the intermediates a working-set model leaves out grow with
it: at 256 antennas the simulator's and the terrestrial fit's tasks held ~4.7x theirs); else
``a = 1`` (small runs alone cannot tell a slope from their overheads, and a slope fitted on them and
extrapolated 20x would refuse runs that fit) and ``b`` the median measured excess over ``W``
(>= 0); ``c, d`` a least-squares line (``d >= 0``; runs of one size: ``d = 0``).
The SGEMM peak measured at fit time is kept with them, and the plan scales its times by it.

A run's measurements outlive its directory as a *record* (:func:`record`, ``mmflow plan --record
RUN_DIR``): its configuration and, per stage, the task count, the largest task's memory above its
worker's baseline and the mean seconds per task. ``--fit`` and ``--against`` take a record file
wherever they take a run directory; the records the package's constants were fitted to lie in
``plan_runs/`` beside this module, so the constants can be refitted, and checked, without the runs.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mmflow.errors import InputError
from mmflow.workflow.config import WorkflowConfig, load_config
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.plan import WORKER_BASE_BYTES, geometry, plan, stage_work
from mmflow.workflow.rundir import RunDir


#: the folder of the records the package's constants were fitted to
RECORDS_DIR = Path(__file__).with_name("plan_runs")


def record(run_dir, sgemm_gflops=None, note=""):
    """What one finished run measured, as a JSON-able record: ``{"source", "note", "sgemm_gflops",
    "config", "stages": {stage: {"tasks", "task_memory_bytes", "task_seconds"}}}`` (the SGEMM peak
    measured beside the run, or None; the configuration as the run resolved it; per stage the tasks
    with resource readings, the largest task's memory above its worker's baseline, the mean seconds
    per task)."""
    run = RunDir(run_dir)
    cfg = load_config(run.path / "config.yaml")
    stages = {}
    for stage in _finished_stages(run):
        infos = [i for i in run.task_infos(stage).values()
                 if i.get("peak_rss_gb") is not None and i.get("rss_start_gb") is not None]
        if infos:
            mem = max(i["peak_rss_gb"] - i["rss_start_gb"] for i in infos) * 1e9
            stages[stage] = {"tasks": len(infos), "task_memory_bytes": max(mem, 0.0),
                             "task_seconds": float(np.mean([i["seconds"] for i in infos]))}
    return {"source": str(run_dir), "note": note, "sgemm_gflops": sgemm_gflops, "config": cfg.model_dump(mode="json"),
            "stages": stages}


def load_record(source):
    """A record (:func:`record`) from a run directory or from a record file (``*.json``)."""
    path = Path(source)
    if path.is_file():
        with open(path) as fh:
            rec = json.load(fh)
        if not isinstance(rec, dict) or "config" not in rec or "stages" not in rec:
            raise InputError(str(path), "config, stages", "not a run's record (mmflow plan --record RUN_DIR)",
                             "give a finished run directory or a file written by mmflow plan --record")
        return rec
    return record(path)


def record_config(rec):
    """The configuration of a record."""
    return WorkflowConfig.model_validate(rec["config"])


def samples(source, sgemm_gflops=None):
    """``{stage: (W, U, memory_bytes, seconds_per_task)}`` measured in one finished run (its directory
    or its record), ``W`` and ``U`` from the run's configuration by today's work model; with
    ``sgemm_gflops``, the seconds a run whose record states the peak beside it would have taken at
    that peak (``seconds x peak_run / sgemm_gflops``)."""
    rec = source if isinstance(source, dict) else load_record(source)
    scale = rec["sgemm_gflops"] / sgemm_gflops if sgemm_gflops and rec.get("sgemm_gflops") else 1.0
    cfg = record_config(rec)
    g = geometry(cfg)
    out = {}
    for stage, m in rec["stages"].items():
        try:
            _, w, u, _ = stage_work(stage, g, cfg)
        except KeyError:
            continue
        out[stage] = (w, u, m["task_memory_bytes"], m["task_seconds"] * scale)
    return out


def _finished_stages(run):
    return [st.name for st in PIPELINE if (run.status_dir(st.name) / "complete.json").exists()]


def _fit(x, y):
    """``(slope, intercept >= 0)`` of ``y ~ slope x + intercept``; through 0 for one distinct x."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(set(np.round(x, 6))) < 2:
        return float(np.sum(x * y) / max(np.sum(x * x), 1e-300)), 0.0
    slope, icpt = np.polyfit(x, y, 1)
    if icpt < 0:  # a negative baseline is unphysical: refit through the origin
        return float(np.sum(x * y) / np.sum(x * x)), 0.0
    if slope < 0:  # no growth measured: the intercept alone
        return 0.0, float(np.mean(y))
    return float(slope), float(icpt)


#: the ratio of the largest to the smallest working set above which memory's slope is fitted
SLOPE_SPAN = 4.0


def fit_memory(w, mem):
    """``(a, b)`` of ``mem ~ a w + b`` (module docstring): fitted where ``w`` spans :data:`SLOPE_SPAN`,
    ``a >= 1``, ``b >= 0``; else ``a = 1``, ``b`` the median excess ``mem - w`` (>= 0)."""
    w, mem = np.asarray(w, float), np.asarray(mem, float)
    if len(w) > 1 and w.min() > 0 and w.max() / w.min() >= SLOPE_SPAN:
        a, b = _fit(w, mem)
        if a >= 1.0:
            return a, b
    return 1.0, max(0.0, float(np.median(mem - w)))


def fit_costs(run_dirs, sgemm_gflops):
    """The constants file's content fitted to ``run_dirs`` (run directories or records; see the module
    docstring) at the SGEMM peak ``sgemm_gflops``: a record's times are first scaled from the peak
    measured beside its run to this one."""
    per_stage = {}
    for d in run_dirs:
        for stage, s in samples(d, sgemm_gflops).items():
            per_stage.setdefault(stage, []).append(s)
    stages = {}
    for stage, ss in per_stage.items():
        w, u, mem, sec = (np.array(v, float) for v in zip(*ss))
        a, b = fit_memory(w, mem)
        c, d = _fit(u, sec)
        stages[stage] = {"a": a, "b": b, "c": c, "d": d, "runs": len(ss)}
    return {"sgemm_gflops": sgemm_gflops, "fitted_on": [_name(d) for d in run_dirs], "stages": stages}


def _name(source):
    """A fitted-on entry: a record in :data:`RECORDS_DIR` by its file name, anything else by its path."""
    path = Path(source)
    return path.name if path.is_file() and path.resolve().parent == RECORDS_DIR.resolve() else str(source)


def write_costs(costs, path):
    with open(path, "w") as fh:
        json.dump(costs, fh, indent=2, sort_keys=True)


def plan_against_run(run_dir, costs=None, peak_gflops=None):
    """The plan of a finished run's configuration (its directory or its record) beside what its tasks
    measured, per stage.

    Per task, as :func:`samples` measures them from the task markers (they survive resumes, so a
    run finished over several invocations counts every task): the mean seconds against the plan's
    ``c U + d`` (scaled from the constants' SGEMM peak to ``peak_gflops``, default the peak its record
    states beside the run, else the peak measured now), and the largest task's memory above its worker's baseline, plus the plan's worker
    baseline, against the plan's task memory. Returns ``(rows, peak_gflops)``; each row
    ``{stage, tasks, planned_task_s, measured_task_s, time_ratio, planned_task_gb, measured_task_gb,
    memory_ratio}`` (ratios measured / planned).
    """
    rec = load_record(run_dir)
    cfg = record_config(rec)
    res = plan(cfg, costs, peak_gflops or rec.get("sgemm_gflops"))
    workers = max(res["task_slots"], 1)  # the plan's stage time is its per-task time x ceil(tasks / workers)
    measured = samples(rec)
    rows = []
    for e in res["stages"]:
        if e["stage"] not in measured:
            continue
        _, _, mem, sec = measured[e["stage"]]
        planned_s = e["seconds"] / -(-e["tasks"] // workers) if e["seconds"] else None
        planned_gb = (e["task_bytes"] + WORKER_BASE_BYTES) / 1e9
        measured_gb = (mem + WORKER_BASE_BYTES) / 1e9
        rows.append({"stage": e["stage"], "tasks": e["tasks"], "planned_task_s": planned_s, "measured_task_s": sec,
                     "time_ratio": sec / planned_s if planned_s else None, "planned_task_gb": planned_gb,
                     "measured_task_gb": measured_gb, "memory_ratio": measured_gb / planned_gb})
    return rows, res["sgemm_gflops"]


def format_against(rows, peak_gflops):
    """:func:`plan_against_run` as a table (ratios measured / planned)."""
    def num(v, fmt):
        return format(v, fmt) if v is not None else "-"

    out = [f"planned at {peak_gflops:.0f} SGEMM GFLOP/s; per task:",
           f"{'stage':12s} {'tasks':>6s} {'plan s':>8s} {'run s':>8s} {'ratio':>6s} {'plan GB':>8s} {'run GB':>7s} "
           f"{'ratio':>6s}"]
    for r in rows:
        out.append(f"{r['stage']:12s} {r['tasks']:6d} {num(r['planned_task_s'], '8.1f')} {r['measured_task_s']:8.1f} "
                   f"{num(r['time_ratio'], '6.2f')} {r['planned_task_gb']:8.2f} {r['measured_task_gb']:7.2f} "
                   f"{r['memory_ratio']:6.2f}")
    return "\n".join(out)
