"""Fit the plan's per-stage constants to measured runs (``mmflow plan --fit RUN_DIR ...``).

Every finished task records in its marker the seconds it took, the resident memory of its worker
when it started (``rss_start_gb``) and the worker's peak while it ran (``peak_rss_gb``,
:mod:`mmflow.workflow.engine.resources`). For each stage and run this gives one sample: the largest task's
memory above its worker's baseline, ``max(peak - start)``, and the mean seconds per task. Against
the stage's modelled working set ``W`` and work units ``U`` (:func:`mmflow.workflow.plan.planner.stage_work`
of the run's own configuration) the constants of

    memory = a W + b,     seconds = c U + d

are fitted over the runs as the lines of least *largest relative error* (:func:`minimax_line`: the
criterion the plan is held to, each run within 25 % in memory and 50 % in time; a least-squares
line lets the paper-scale run set the constants and missed the demo's tasks by 3.6x): memory's
slope ``a >= 1`` where the runs' working sets span at least :data:`SLOPE_SPAN` (a paper-scale run
beside small ones; a task holds at least its working set, and the intermediates a working-set model
leaves out grow with it: at 256 antennas the simulator's and the terrestrial fit's tasks held ~4.7x
theirs), else ``a = 1`` (small runs alone cannot tell a slope from their overheads, and a slope
fitted on them and extrapolated 20x would refuse runs that fit); ``b, c, d >= 0``.
The reference SGEMM peak (:func:`reference_peak`) is kept with them, and the plan scales its times
by it.

A run's measurements outlive its directory as a *record* (:func:`record`, ``mmflow plan --record
RUN_DIR``): its configuration and, per stage, the task count, the largest task's memory above its
worker's baseline and the mean seconds per task (and the SGEMM peak measured beside the run). ``--fit`` and
``--against`` take a record file
wherever they take a run directory; the records the package's constants were fitted to lie in
``plan/records/`` beside this module, so the constants can be refitted, and checked, without the runs.
A record's ``superseded`` (``{stage: why}``) names the stages whose code has changed since the run
measured them (the peel stage 4x faster, say): their figures no longer describe the code, and they
enter neither the fit nor the check (:func:`samples`), while the record's other stages still do. Its
``memory_superseded`` (``{stage: why}``) names the stages whose tasks' memory has changed but not their
time: only their seconds enter the fit and the check. A stage whose memory no record measures keeps
``a = 1, b = 0``: its plan is its cost model's working set.
"""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from mmflow.errors import InputError
from mmflow.workflow.engine.ingest_plan import ingest_plan
from mmflow.telescope.layout import Layout
from mmflow.workflow.config.schema import WorkflowConfig, load_config
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.plan.planner import WORKER_BASE_BYTES, geometry, plan, stage_work
from mmflow.workflow.engine.rundir import RunDir


#: the folder of the records the package's constants were fitted to
RECORDS_DIR = Path(__file__).with_name("records")


def record(run_dir, sgemm_gflops=None, note=""):
    """What one finished run measured, as a JSON-able record: ``{"source", "note", "sgemm_gflops",
    "config", "stages": {stage: {"tasks", "task_memory_bytes", "task_seconds"}}, "task_threads"}`` (the
    SGEMM peak measured beside the run, or None; the configuration as the run resolved it; per stage the
    tasks with resource readings, the largest task's memory above its worker's baseline, the mean seconds
    per task; the most threads a task ran on, :func:`mmflow.threads.n_threads` as each task recorded it)."""
    run = RunDir(run_dir)
    cfg = load_config(run.path / "config.yaml")
    stages, threads = {}, 1
    for stage in _finished_stages(run):
        every = run.task_infos(stage).values()
        threads = max([threads] + [i["threads"] for i in every if "threads" in i])
        infos = [i for i in every if i.get("peak_rss_gb") is not None and i.get("rss_start_gb") is not None]
        if infos:
            mem = max(i["peak_rss_gb"] - i["rss_start_gb"] for i in infos) * 1e9
            stages[stage] = {"tasks": len(infos), "task_memory_bytes": max(mem, 0.0),
                             "task_seconds": float(np.mean([i["seconds"] for i in infos]))}
    rec = {"source": str(run_dir), "note": note, "sgemm_gflops": sgemm_gflops, "config": cfg.model_dump(mode="json"),
           "stages": stages, "task_threads": threads}
    if cfg.source == "ingest":
        rec["ingest"] = ingest_geometry(ingest_plan(cfg))
    return rec


def ingest_geometry(plan):
    """What the plan reads of an ingest plan (:class:`mmflow.io.ingest.IngestPlan`), JSON-able: a record of
    an ingested run keeps it, so that it plans without the telescope's files (:func:`record_ingest`)."""
    lay = plan.layout
    pairs = np.asarray(plan.pairs)
    every = _every_pair(len(lay.names))  # the usual case, kept as a word: 32,896 pairs at 256 antennas
    return {"n_time": int(plan.n_time), "integration_s": float(plan.integration_s), "pols": list(plan.pols),
            "freqs_hz": [float(f) for f in plan.freqs_hz],
            "pairs": EVERY_PAIR if pairs.shape == every.shape and np.array_equal(pairs, every) else pairs.tolist(),
            "layout": {"names": list(lay.names), "enu": np.asarray(lay.enu).tolist(), "lat_deg": float(lay.lat_deg),
                       "lon_deg": float(lay.lon_deg), "height_m": float(lay.height_m)}}


#: a record's ``ingest.pairs`` when the files hold every pair ``i <= j`` of their antennas, in that order
EVERY_PAIR = "every i <= j"


def _every_pair(n):
    i, j = np.triu_indices(n)
    return np.stack([i, j], axis=1)


def record_ingest(rec):
    """A record's copy of its files' ingest plan
    (:func:`ingest_geometry`) for :func:`mmflow.workflow.plan.planner.geometry`,
    or None (a simulation, or a record without one: the files are read)."""
    ing = rec.get("ingest")
    if not ing:
        return None
    lay = ing["layout"]
    layout = Layout(lay["names"], np.asarray(lay["enu"]), lay["lat_deg"], lay["lon_deg"], lay["height_m"],
                    provenance=f"the record of {rec.get('source')}")
    pairs = _every_pair(len(lay["names"])) if ing["pairs"] == EVERY_PAIR else np.asarray(ing["pairs"])
    return SimpleNamespace(n_time=ing["n_time"], integration_s=ing.get("integration_s"), pols=ing["pols"],
                           freqs_hz=np.asarray(ing["freqs_hz"]), pairs=pairs, layout=layout)


def load_record(source):
    """A record (:func:`record`) from a run directory or from a record file (``*.json``); a record
    itself is returned as it is."""
    if isinstance(source, dict):
        return source
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


def samples(source):
    """``{stage: (W, U, memory_bytes, seconds_per_task)}`` measured in one finished run (its directory
    or its record; not the record's ``superseded`` stages, and ``memory_bytes`` None for its
    ``memory_superseded`` ones), ``W`` and ``U`` from the run's configuration by today's work model."""
    rec = load_record(source)
    cfg = record_config(rec)
    g = geometry(cfg, record_ingest(rec), rec.get("task_threads", 1))  # records before it ran one thread a task
    out = {}
    for stage, m in rec["stages"].items():
        if stage in rec.get("superseded", {}):  # measured with code since changed
            continue
        try:
            _, w, u, _ = stage_work(stage, g, cfg)
        except KeyError:
            continue
        mem = None if stage in rec.get("memory_superseded", {}) else m["task_memory_bytes"]
        out[stage] = (w, u, mem, m["task_seconds"])
    return out


def _finished_stages(run):
    return [st.name for st in PIPELINE if (run.status_dir(st.name) / "complete.json").exists()]


def minimax_line(x, y, offset=0.0, slope=(0.0, None)):
    """``(s, c)``, ``c >= 0``, ``s`` within ``slope`` (bounds, or one value), minimising the largest
    relative error of the line over the points: ``max_i |s x_i + c - y_i| / (y_i + offset)`` (a
    linear programme in ``(s, c, t)``). This is the criterion the plan is held to (each run within
    25 % in memory, 50 % in time), where a least-squares line lets the largest run set the constants
    and misses the small ones by 3x. ``offset``: what both sides of the ratio hold besides the line
    (the worker's baseline for memory)."""
    from scipy.optimize import linprog  # deferred: scipy.optimize only for a refit

    x, y = np.asarray(x, float), np.asarray(y, float)
    d = y + offset
    lo, hi = (slope, slope) if np.isscalar(slope) else slope
    a_ub = np.concatenate(
        [np.stack([x / d, 1 / d, -np.ones_like(x)], 1), np.stack([-x / d, -1 / d, -np.ones_like(x)], 1)]
    )
    b_ub = np.concatenate([y / d, -y / d])
    # unknowns in units of the data (slope x max(x) / max(y), intercept / max(y)): a well-scaled programme
    xs, ys = max(float(np.max(np.abs(x))), 1e-300), max(float(np.max(d)), 1e-300)
    a_ub[:, 0] *= ys / xs
    a_ub[:, 1] *= ys
    res = linprog([0, 0, 1], A_ub=a_ub, b_ub=b_ub, method="highs",
                  bounds=[(lo * xs / ys, None if hi is None else hi * xs / ys), (0, None), (0, None)])
    if not res.success:
        raise RuntimeError(f"minimax line fit failed: {res.message}")
    return float(res.x[0] * ys / xs), float(res.x[1] * ys)


#: the ratio of the largest to the smallest working set above which memory's slope is fitted
SLOPE_SPAN = 4.0
#: seconds per task below which a run's time is not held to a relative bound (scheduling noise)
TIME_FLOOR_S = 0.05


def fit_memory(w, mem, offset=0.0):
    """``(a, b)`` of ``mem ~ a w + b`` (module docstring): the line of least largest relative error
    (:func:`minimax_line`, ``offset`` the worker's baseline on both sides); ``a >= 1`` fitted where
    ``w`` spans :data:`SLOPE_SPAN`, else ``a = 1``; ``b >= 0``."""
    w, mem = np.asarray(w, float), np.asarray(mem, float)
    spans = len(w) > 1 and w.min() > 0 and w.max() / w.min() >= SLOPE_SPAN
    return minimax_line(w, mem, offset, (1.0, None) if spans else 1.0)


def fit_time(u, sec):
    """``(c, d)`` of ``sec ~ c u + d``, ``c, d >= 0``, of least largest relative error (each task time
    counted as at least :data:`TIME_FLOOR_S`)."""
    return minimax_line(u, np.maximum(np.asarray(sec, float), TIME_FLOOR_S))


def fit_costs(run_dirs, sgemm_gflops):
    """The constants file's content fitted to ``run_dirs`` (run directories or records; see the module
    docstring), every run taken as run at the SGEMM peak ``sgemm_gflops`` (:func:`reference_peak`)."""
    per_stage = {}
    for d in run_dirs:
        for stage, s in samples(d).items():
            per_stage.setdefault(stage, []).append(s)
    stages = {}
    for stage, ss in per_stage.items():
        w, u, mem, sec = (np.array(v, float) for v in zip(*ss))
        known = ~np.isnan(mem)  # memory_superseded: None
        a, b = fit_memory(w[known], mem[known], WORKER_BASE_BYTES) if known.any() else (1.0, 0.0)
        c, d = fit_time(u, sec)
        stages[stage] = {"a": a, "b": b, "c": c, "d": d, "runs": len(ss)}
    return {"sgemm_gflops": sgemm_gflops, "fitted_on": [_name(d) for d in run_dirs], "stages": stages}


def _name(source):
    """A fitted-on entry: a record in :data:`RECORDS_DIR` by its file name, anything else by its path
    (a record given as such: its run's)."""
    if isinstance(source, dict):
        return source["source"]
    path = Path(source)
    return path.name if path.is_file() and path.resolve().parent == RECORDS_DIR.resolve() else str(source)


def reference_peak(run_dirs, measure):
    """The SGEMM peak a fit's runs are taken to have run at: the median of the peaks their records state
    beside them, else ``measure()`` (the peak now). A 0.1 s SGEMM snapshot swings ~2x on a shared VM
    while the stages' times do not (the reduced run measured 103 GFLOP/s before it, the next one 207,
    with the same seconds per task), so a run's own snapshot does not rescale its times."""
    peaks = [r["sgemm_gflops"] for r in map(load_record, run_dirs) if r.get("sgemm_gflops")]
    return float(np.median(peaks)) if peaks else float(measure())


def write_costs(costs, path):
    with open(path, "w") as fh:
        json.dump(costs, fh, indent=2, sort_keys=True)
        fh.write("\n")


def plan_against_run(run_dir, costs=None, peak_gflops=None):
    """The plan of a finished run's configuration (its directory or its record) beside what its tasks
    measured, per stage.

    Per task, as :func:`samples` measures them from the task markers (they survive resumes, so a
    run finished over several invocations counts every task): the mean seconds against the plan's
    ``c U + d`` (scaled from the constants' SGEMM peak to ``peak_gflops``, default the peak its record
    states beside the run, else the peak measured now), and the largest task's memory above its worker's baseline, plus
    the plan's worker
    baseline, against the plan's task memory. Returns ``(rows, peak_gflops)``; each row
    ``{stage, tasks, planned_task_s, measured_task_s, time_ratio, planned_task_gb, measured_task_gb,
    memory_ratio}`` (ratios measured / planned).
    """
    rec = load_record(run_dir)
    cfg = record_config(rec)
    res = plan(cfg, costs, peak_gflops or rec.get("sgemm_gflops"), record_ingest(rec))
    workers = max(res["task_slots"], 1)  # the plan's stage time is its per-task time x ceil(tasks / workers)
    measured = samples(rec)
    rows = []
    for e in res["stages"]:
        if e["stage"] not in measured:
            continue
        _, _, mem, sec = measured[e["stage"]]
        planned_s = e["seconds"] / -(-e["tasks"] // workers) if e["seconds"] else None
        planned_gb = (e["task_bytes"] + WORKER_BASE_BYTES) / 1e9
        measured_gb = None if mem is None else (mem + WORKER_BASE_BYTES) / 1e9
        rows.append({"stage": e["stage"], "tasks": e["tasks"], "planned_task_s": planned_s, "measured_task_s": sec,
                     "time_ratio": sec / planned_s if planned_s else None, "planned_task_gb": planned_gb,
                     "measured_task_gb": measured_gb,
                     "memory_ratio": None if measured_gb is None else measured_gb / planned_gb})
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
                   f"{num(r['time_ratio'], '6.2f')} {r['planned_task_gb']:8.2f} {num(r['measured_task_gb'], '7.2f')} "
                   f"{num(r['memory_ratio'], '6.2f')}")
    return "\n".join(out)
