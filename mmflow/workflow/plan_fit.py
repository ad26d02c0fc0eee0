"""Fit the plan's per-stage constants to measured runs (``mmflow plan --fit RUN_DIR ...``).

Every finished task records in its marker the seconds it took, the resident memory of its worker
when it started (``rss_start_gb``) and the worker's peak while it ran (``peak_rss_gb``,
:mod:`mmflow.workflow.resources`). For each stage and run this gives one sample: the largest task's
memory above its worker's baseline, ``max(peak - start)``, and the mean seconds per task. Against
the stage's modelled working set ``W`` and work units ``U`` (:func:`mmflow.workflow.plan.stage_work`
of the run's own configuration) the constants of

    memory = a W + b,     seconds = c U + d

are fitted over the runs: ``a = 1`` (a task holds its working set; small runs cannot tell a slope
from their overheads, and a fitted slope extrapolated 20x to the paper's channel would refuse runs
that fit), ``b`` the median measured excess over ``W`` (>= 0); ``c, d`` a least-squares line
(``d >= 0``; runs of one size: ``d = 0``).
The SGEMM peak measured at fit time is kept with them, and the plan scales its times by it.
"""
from __future__ import annotations

import json

import numpy as np

from mmflow.workflow.config import load_config
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.plan import geometry, stage_work
from mmflow.workflow.rundir import RunDir


def samples(run_dir):
    """``{stage: (W, U, memory_bytes, seconds_per_task)}`` measured in one finished run."""
    run = RunDir(run_dir)
    cfg = load_config(run.path / "config.yaml")
    g = geometry(cfg)
    out = {}
    for stage in _finished_stages(run):
        infos = [i for i in run.task_infos(stage).values()
                 if i.get("peak_rss_gb") is not None and i.get("rss_start_gb") is not None]
        if not infos:
            continue
        try:
            _, w, u, _ = stage_work(stage, g, cfg)
        except KeyError:
            continue
        mem = max(i["peak_rss_gb"] - i["rss_start_gb"] for i in infos) * 1e9
        sec = float(np.mean([i["seconds"] for i in infos]))
        out[stage] = (w, u, max(mem, 0.0), sec)
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


def fit_costs(run_dirs, sgemm_gflops):
    """The constants file's content fitted to ``run_dirs`` (see the module docstring)."""
    per_stage = {}
    for d in run_dirs:
        for stage, s in samples(d).items():
            per_stage.setdefault(stage, []).append(s)
    stages = {}
    for stage, ss in per_stage.items():
        w, u, mem, sec = (np.array(v, float) for v in zip(*ss))
        a, b = 1.0, max(0.0, float(np.median(mem - w)))  # the working set itself, plus the stage's overhead
        c, d = _fit(u, sec)
        stages[stage] = {"a": a, "b": b, "c": c, "d": d, "runs": len(ss)}
    return {"sgemm_gflops": sgemm_gflops, "fitted_on": [str(d) for d in run_dirs], "stages": stages}


def write_costs(costs, path):
    with open(path, "w") as fh:
        json.dump(costs, fh, indent=2, sort_keys=True)
