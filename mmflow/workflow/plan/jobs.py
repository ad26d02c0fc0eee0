"""A run laid onto a batch cluster's nodes: ``mmflow plan WORKFLOW --cluster slurm``.

From the plan of every stage (:mod:`mmflow.workflow.plan.planner`: the largest task's memory, its time)
and a node's cores and memory (:mod:`mmflow.workflow.plan.nodes`), per stage:

- **the worker**: a standard worker is one core with a core's share of the node's memory; a stage whose
  largest task (with a worker's baseline) needs more gets workers of ``k`` cores and ``k`` shares, the
  fewest that hold it below dask's kill threshold (:func:`terminate_fraction`), so a node runs
  ``cores // k`` of them;
- **the split**: a stage whose largest task needs more than a whole node is re-planned with the settings
  its cost model offers (:attr:`mmflow.workflow.plan.work.Cost.split`: ``transfer.baseline_chunk``,
  ``transfer.m_block``, ``mmode.baseline_chunk``, ...), in order, until it fits; the setting chosen is
  stated, and applies to every stage (all are re-planned with it). Where even the last does not fit
  the run is refused, naming the stage, its memory and the node's;
- **the jobs**: per stage one job per node it can fill, of the stage's workers on that node (``cores``,
  ``memory``: their shares and the job's own ``dask worker`` process,
  :data:`mmflow.workflow.plan.nodes.JOB_PROCESS_BYTES`; ``processes``), and a walltime of
  :data:`WALLTIME_MARGIN` times the stage's planned time on the nodes plus :data:`JOB_START_S`;
- **the nodes**: as given (``--nodes``), else the fewest whose planned wall time is within
  :data:`NEAR_FASTEST` of the time with every stage's tasks in one round (at most the partition's nodes).

Time: the constants were fitted on a machine of ``R`` task slots (one core each; ``R`` from the fit's
records) whose SGEMM peak ``P`` was all of them, so a task on one core of a node of per-core peak ``p``
takes ``(c U + d) (P / R) / p``; on a larger worker too (its task's kernels may use its ``k`` cores,
:mod:`mmflow.threads`, but how well each stage's do is not measured: the plan's time is the one-core
upper bound, so the walltime asked for is safe). ``p``: the node's SGEMM peak over its cores
(``--node-peak``), else this machine's per core.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from mmflow.errors import InputError
from mmflow.workflow.config.schema import WorkflowConfig
from mmflow.workflow.engine.context import build_telescope
from mmflow.workflow.engine.geometry import n_integrations
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.plan.nodes import Node, job_memory
from mmflow.workflow.plan.planner import (COSTS_FILE, WORKER_BASE_BYTES, duration, estimate, free_disk_gb, geometry,
                                          load_costs, run_live_stores, task_seconds)

#: the job's walltime against the stage's planned time (the plan is within 50 % in time: docs/planning.md)
WALLTIME_MARGIN = 2.0
#: seconds a job is given beyond its work: the worker's start (imports, numba's cache) and the stage's end
JOB_START_S = 600.0
#: walltimes are rounded up to this many seconds
WALLTIME_STEP_S = 900
#: the default node count: the fewest nodes whose wall time is within this factor of the fastest
NEAR_FASTEST = 1.10
#: the polarisations an ingest planned without its files keeps: the parallel hands (the cross hands,
#: where the files hold them, ride beside them: ``vis.zarr``'s ``vis_cross``)
LAYOUT_POLS = ("xx", "yy")


def with_settings(cfg, settings):
    """``cfg`` with dotted settings replaced (``{"transfer.m_block": 8}``), validated again."""
    data = cfg.model_dump(mode="json")
    for key, value in settings.items():
        *path, last = key.split(".")
        node = data
        for part in path:
            node = node[part]
        node[last] = value
    return WorkflowConfig.model_validate(data)


def layout_ingest(cfg):
    """An ingest plan (:func:`mmflow.workflow.plan.planner.geometry`'s ``ingest``) of the workflow's own
    array without its files: the telescope's layout and baselines (``telescope``), one sidereal day of
    ``observation.integration_s`` (or ``observation.n_integrations``), ``observation.freqs_mhz`` and
    :data:`LAYOUT_POLS`. What ``--simulate-layout`` plans an ingesting workflow with."""
    tel = build_telescope(cfg)
    return SimpleNamespace(n_time=n_integrations(cfg), pols=list(LAYOUT_POLS), freqs_hz=np.asarray(tel.freqs_hz),
                           pairs=np.asarray(tel.antenna_pairs()), layout=tel.layout)


def reference_slots(costs):
    """The task slots (workers x threads) of the runs the constants were fitted on: the median over
    the fit's records in ``plan/records/`` (1 where none is found: tasks timed at the whole peak)."""
    slots = []
    for name in costs.get("fitted_on", []):
        path = COSTS_FILE.parent / "records" / name
        if path.is_file():
            c = json.loads(path.read_text())["config"].get("cluster", {})
            slots.append(c.get("n_workers", 1) * c.get("threads_per_worker", 1))
    return float(np.median(slots)) if slots else 1.0


def terminate_fraction():
    """The share of its memory limit at which dask's nanny kills a worker
    (``distributed.worker.memory.terminate``, 0.95 by default): a task must stay below it."""
    import dask.config  # deferred: dask takes 0.3-0.8 s to import
    import distributed  # noqa: F401  -- loads distributed's defaults into dask's configuration

    return float(dask.config.get("distributed.worker.memory.terminate", 0.95) or 1.0)


def _worker_cores(need, node, frac):
    """Cores of the fewest core-shares of a node whose memory, below dask's ``frac``, holds ``need``
    bytes (more than the node's cores: no fit)."""
    return max(1, math.ceil(need / (node.core_memory_bytes * frac) - 1e-9))


def _sized(name, g, cfg, costs, peak, total, node, frac):
    """A stage's task estimate and its worker's cores ``k``: a ``k``-core worker runs its one task's kernels
    on ``k`` threads (:func:`mmflow.threads.concurrent_tasks`), so a task whose memory grows with its
    threads (the solver's per-thread factors) is estimated again at ``k`` threads until ``k`` holds it."""
    est = estimate(name, g, cfg, costs, peak, 1, total)
    k = _worker_cores(est.task_bytes + WORKER_BASE_BYTES, node, frac)
    while g.task_threads < k <= node.cores:  # k grows each pass: at most node.cores passes
        at_k = estimate(name, dataclasses.replace(g, task_threads=k), cfg, costs, peak, 1, total)
        wider = _worker_cores(at_k.task_bytes + WORKER_BASE_BYTES, node, frac)
        if wider <= k:
            return at_k, k
        k = wider
    return est, k  # one thread's task, or one that no node holds (the row says it does not fit)


def stage_rows(cfg, g, node, nodes, core_gflops, costs, slots):
    """Per enabled stage its worker, its time on ``nodes`` nodes and what scales it (dicts).

    ``core_gflops``: a node's SGEMM peak per core; ``slots``: :func:`reference_slots`. A row's time on
    any node count is :func:`stage_seconds`: ``per_task_s`` a round of tasks, and ``node_s`` (a
    :attr:`Cost.seconds` hook's stage-wide sums, e.g. the diffuse sky's) over the nodes.
    """
    rows, frac, peak = [], terminate_fraction(), slots * core_gflops
    total = nodes * node.cores * core_gflops
    for st in PIPELINE:
        if not st.enabled(cfg) or st.task is None:
            continue
        est, k = _sized(st.name, g, cfg, costs, peak, total, node, frac)
        need = est.task_bytes + WORKER_BASE_BYTES
        k_s = costs["stages"].get(st.name)
        per_task = task_seconds(k_s, est.units_per_task, costs, peak) if k_s else 0.0
        # the stage-wide part: what is left with every task in one round
        wide = estimate(st.name, g, cfg, costs, peak, max(est.tasks, 1), total).seconds - per_task
        rows.append({"stage": st.name, "tasks": est.tasks, "task_gb": need / 1e9, "worker_cores": k,
                     "workers_per_node": max(1, node.cores // k), "worker_memory_gb": k * node.core_memory_bytes / 1e9,
                     "fits": k <= node.cores, "per_task_s": per_task, "node_s": max(0.0, wide) * nodes,
                     "store_gb": est.store_bytes / 1e9, "stores": est.stores, "arrays": est.arrays,
                     "channels": est.channels, "store_files": est.store_files,
                     "largest_chunk_mb": est.largest_chunk_bytes / 1e6, "notes": est.notes})
    return rows


def stage_seconds(row, nodes):
    """A stage's planned wall time on ``nodes`` nodes (its rounds of tasks, and its stage-wide sums)."""
    return row["per_task_s"] * math.ceil(row["tasks"] / (nodes * row["workers_per_node"])) + row["node_s"] / nodes


def _fastest_nodes(rows, node):
    most = max(math.ceil(r["tasks"] / r["workers_per_node"]) for r in rows)
    return min(most, node.count) if node.count else most


def choose_nodes(rows, node):
    """The fewest nodes whose wall time is within :data:`NEAR_FASTEST` of the fastest."""
    most = _fastest_nodes(rows, node)
    best = sum(stage_seconds(r, most) for r in rows)
    return next(n for n in range(1, most + 1) if sum(stage_seconds(r, n) for r in rows) <= NEAR_FASTEST * best)


def _split(cfg, row, node, replan):
    """The first of the stage's split settings under which its largest task fits a node, with its row;
    refused (an :class:`InputError` naming the limit) where none does."""
    cost = PIPELINE.stage(row["stage"]).cost
    tried, need = None, row["task_gb"]
    for settings in cost.split_settings(cfg):
        r = next(x for x in replan(with_settings(cfg, settings)) if x["stage"] == row["stage"])
        if r["fits"]:
            return settings
        tried, need = settings, r["task_gb"]
    last = (" even with " + ", ".join(f"{k}={v}" for k, v in tried.items())) if tried else " (no setting splits it)"
    frac = terminate_fraction()
    hold = node.core_memory_bytes * node.cores * frac / 1e9
    raise InputError("workflow", f"stage {row['stage']}", f"its largest task needs ~{need:.2f} GB{last} (`mmflow "
                     f"plan`), more than the {hold:.2f} GB a worker may hold on a node of {node.memory_bytes / 1e9:.2f}"
                     f" GB (whole GiB to a job; dask stops a worker at {frac:.0%} of its memory)",
                     f"{cost.shrink_setting(cfg)}, or nodes with more memory (--node-memory)")


def configured_worker_gb(cfg):
    """The memory of a worker the workflow's own ``cluster.jobqueue`` asks for (``memory`` over
    ``processes``), or None where it does not give both."""
    from dask.utils import parse_bytes  # deferred: dask takes 0.3-0.8 s to import

    jq = cfg.cluster.jobqueue or {}
    if jq.get("memory") is None or jq.get("processes") is None:
        return None
    mem = parse_bytes(jq["memory"]) if isinstance(jq["memory"], str) else float(jq["memory"])
    return mem / max(1, int(jq["processes"])) / 1e9


def cluster_plan(cfg, node, nodes=None, costs=None, peak_gflops=None, node_gflops=None, ingest=None):
    """The run laid onto nodes of ``node``'s size (see the module's docstring).

    Parameters
    ----------
    cfg : WorkflowConfig
    node : mmflow.workflow.plan.nodes.Node
    nodes : int, optional
        Nodes to plan on (default: :func:`choose_nodes`).
    costs : dict, optional
        The fitted constants (default: the package's).
    peak_gflops : float, optional
        This machine's SGEMM peak (measured where not given), for nodes of its per-core speed.
    node_gflops : float, optional
        A node's SGEMM peak, all its cores (overrides ``peak_gflops``).
    ingest : object, optional
        As :func:`mmflow.workflow.plan.planner.geometry`'s (e.g. :func:`layout_ingest`).

    Returns
    -------
    dict
        ``node``, ``nodes``, ``settings`` (the split settings chosen, dotted), ``stages`` (rows of
        :func:`stage_rows`), ``jobs`` (:func:`job_shapes`), ``wall_s``, ``store_gb`` (the live stores'
        peak, :func:`mmflow.workflow.plan.planner.run_live_stores`), ``free_disk_gb``
        (where ``run.directory`` will be: the shared file system where planned on a login node),
        ``node_memory_gb`` (the most a node holds at once), ``node_hours`` and ``core_gflops``; where the
        workflow's ``cluster.jobqueue`` gives memory and processes, ``configured_worker_gb`` and the
        stages whose tasks its workers cannot hold (``too_large_for_configured``).

    Raises
    ------
    InputError
        A stage's largest task fits no node even with the last of its split settings.
    """
    from mmflow.machine import gemm_gflops  # deferred: scipy's BLAS
    from mmflow.threads import usable_cores

    costs = costs or load_costs()
    if node_gflops:
        core = node_gflops / node.cores
    else:
        core = (peak_gflops or gemm_gflops(np.float32, n=768)) / usable_cores()
    slots = reference_slots(costs)
    geo = {}

    def replan(c, n=1):
        key = c.model_dump_json()
        if key not in geo:
            geo[key] = geometry(c, ingest)
        return stage_rows(c, geo[key], node, n, core, costs, slots)

    settings, split = {}, set()
    while True:
        c = with_settings(cfg, settings)
        rows = replan(c)
        over = [r for r in rows if not r["fits"]]
        if not over:
            break
        if over[0]["stage"] in split:  # another stage's split undid it: its setting no longer helps
            raise InputError("workflow", f"stage {over[0]['stage']}", f"its largest task needs "
                             f"~{over[0]['task_gb']:.2f} GB with {settings}, more than a node holds",
                             "nodes with more memory (--node-memory)")
        split.add(over[0]["stage"])
        settings.update(_split(c, over[0], node, replan))
    n = nodes or choose_nodes(rows, node)
    rows = replan(c, n)
    res = {"node": {"cores": node.cores, "memory_gb": node.memory_bytes / 1e9,
                    "core_memory_bytes": node.core_memory_bytes, "partition": node.partition,
                    "source": node.source, "available": node.count},
           "nodes": n, "settings": settings, "stages": rows, "core_gflops": core, "reference_slots": slots,
           "store_gb": run_live_stores([(r["stage"], r["stores"], r["arrays"], r["channels"]) for r in rows], c,
                                       {r["stage"]: r["tasks"] for r in rows},
                                       {r["stage"]: n * r["workers_per_node"] for r in rows})[0] / 1e9,
           "store_files": sum(r["store_files"] for r in rows),
           "largest_chunk_mb": max(r["largest_chunk_mb"] for r in rows),
           "free_disk_gb": free_disk_gb(cfg.run.directory)}
    configured = configured_worker_gb(cfg)
    if configured is not None:
        res["configured_worker_gb"] = configured
        res["too_large_for_configured"] = [r["stage"] for r in rows
                                           if r["task_gb"] > configured * terminate_fraction()]
    res.update(totals(res, n))
    res["jobs"] = job_shapes(res, n)
    return res


def stage_jobs(row, nodes):
    """Jobs (nodes) a stage uses on ``nodes`` nodes: no more than its tasks fill."""
    return min(nodes, math.ceil(row["tasks"] / row["workers_per_node"]))


def totals(res, nodes):
    """Wall time, the most memory a node holds at once and node-hours of a cluster plan on ``nodes``."""
    rows = res["stages"]
    hours = sum(stage_seconds(r, nodes) * stage_jobs(r, nodes) for r in rows) / 3600
    peak = max(min(r["workers_per_node"], r["tasks"]) * r["task_gb"] for r in rows)
    return {"wall_s": sum(stage_seconds(r, nodes) for r in rows), "node_memory_gb": peak, "node_hours": hours}


def _walltime(seconds):
    s = math.ceil((seconds * WALLTIME_MARGIN + JOB_START_S) / WALLTIME_STEP_S) * WALLTIME_STEP_S
    return f"{s // 3600:02d}:{s % 3600 // 60:02d}:00"


def job_shapes(plan_result, nodes=None):
    """The batch jobs of each stage of a :func:`cluster_plan` on ``nodes`` nodes (default: its own).

    A pure function of the plan: the cluster code asks it for the jobs to submit.

    Returns
    -------
    dict
        ``{stage: {cores, memory, processes, worker_cores, walltime, count, ...}}``: per node one job of
        ``processes`` workers of ``worker_cores`` cores each (``cores`` in all) and ``memory``
        (dask-jobqueue's text in whole MiB, e.g. ``"99200MiB"``: the workers' shares and the job's own process,
        :func:`mmflow.workflow.plan.nodes.job_memory`), ``count`` jobs; neither more jobs nor more workers
        in a job than the stage's tasks fill. ``worker_memory_bytes`` (a worker's shares: dask's limit for it
        is at least these) and
        ``task_memory_bytes`` (the stage's largest task with a worker's baseline) let the cluster code
        route the tasks, e.g. as dask worker resources.
    """
    n = nodes or plan_result["nodes"]
    core_mem = plan_result["node"]["core_memory_bytes"]  # whole MiB: a job asks for whole MiB
    out = {}
    for r in plan_result["stages"]:
        count, k = stage_jobs(r, n), r["worker_cores"]
        p = min(r["workers_per_node"], math.ceil(r["tasks"] / count))  # a job no larger than its tasks fill
        out[r["stage"]] = {"cores": p * k, "memory": job_memory(p * k, core_mem), "processes": p,
                           "worker_cores": k, "walltime": _walltime(stage_seconds(r, n)), "count": count,
                           "worker_memory_bytes": k * core_mem,
                           "task_memory_bytes": math.ceil(r["task_gb"] * 1e9)}
    return out


def worker_pools(plan_result, nodes=None):
    """The jobs a run asks for: :func:`job_shapes` grouped by worker, so that stages of one worker
    shape share their jobs (none resubmitted between them) and larger workers serve only the stages
    that need them.

    Returns
    -------
    dict
        ``{stage: pool}``, one pool dict shared by the stages of its worker: ``worker_cores``,
        ``worker_memory_bytes`` (a worker's limit), ``processes`` (workers a job: the most any of its
        stages fills), ``cores`` and ``memory`` (a job's, as :func:`job_shapes` writes them), ``count``
        (jobs: the most any of its stages uses), ``walltime`` (the longest of its stages'),
        ``task_memory_bytes`` (its stages' largest task with a worker's baseline) and ``stages``.
    """
    shapes = job_shapes(plan_result, nodes)
    core_mem = plan_result["node"]["core_memory_bytes"]
    pools, out = {}, {}
    for stage, j in shapes.items():
        k = j["worker_cores"]
        pool = pools.setdefault(k, {"worker_cores": k, "worker_memory_bytes": j["worker_memory_bytes"],
                                    "processes": 0, "count": 0, "walltime": "00:00:00", "task_memory_bytes": 0,
                                    "stages": []})
        pool["processes"] = max(pool["processes"], j["processes"])
        pool["count"] = max(pool["count"], j["count"])
        pool["walltime"] = max(pool["walltime"], j["walltime"], key=lambda w: [int(x) for x in w.split(":")])
        pool["task_memory_bytes"] = max(pool["task_memory_bytes"], j["task_memory_bytes"])
        pool["stages"].append(stage)
        out[stage] = pool
    for pool in pools.values():
        pool["cores"] = pool["processes"] * pool["worker_cores"]
        pool["memory"] = job_memory(pool["cores"], core_mem)
    return out


def projection(cfg, node, nodes=(8, 64), **kw):
    """A cluster plan projected onto several node counts (JSON-ready): per count the wall time, the
    most memory a node holds at once, the stores and node-hours, and per stage its tasks and their
    planned seconds and memory (the task sizes a per-task overhead is set against); for ``mmflow bench cluster``.

    ``kw``: as :func:`cluster_plan` (``costs``, ``peak_gflops``, ``node_gflops``, ``ingest``).
    """
    res = cluster_plan(cfg, node, nodes[0], **kw)
    out = {"node": res["node"], "settings": res["settings"], "core_gflops": res["core_gflops"],
           "store_gb": res["store_gb"], "store_files": res["store_files"],
           "largest_task": max(res["stages"], key=lambda r: r["task_gb"])["task_gb"],
           "stages": [{"stage": r["stage"], "tasks": r["tasks"], "per_task_s": r["per_task_s"],
                       "task_gb": r["task_gb"]} for r in res["stages"]],
           "nodes": {}}
    for n in nodes:
        out["nodes"][str(n)] = {**totals(res, n), "jobs": job_shapes(res, n)}
    return out


#: the OVRO-LWA's 352-antenna array as a workflow (its files not needed: :func:`layout_ingest`)
ARRAY_WORKFLOW = Path(__file__).resolve().parents[3] / "workflows" / "ovro-lwa-stage3.yaml"
#: the node :func:`array_projection` plans on by default: 32 cores and 128 GB (issue 38's example)
ARRAY_NODE = Node(32, 128e9)


def array_projection(nodes=(8, 64), node=ARRAY_NODE, workflow=ARRAY_WORKFLOW, overrides=(), **kw):
    """:func:`projection` of the 352-antenna array (``workflow``: its workflow, planned on its own
    layout without its files) onto ``nodes`` nodes of ``node``'s size, with the array's sizes: what
    ``mmflow bench cluster`` states beside its measurements. ``kw``: as :func:`cluster_plan`."""
    from mmflow.workflow.config.schema import load_config  # deferred: the schema's validators load dask

    cfg = load_config(workflow, list(overrides))
    ingest = layout_ingest(cfg)
    out = projection(cfg, node, nodes, ingest=ingest, **kw)
    out["array"] = {"workflow": Path(workflow).name, "antennas": len(ingest.layout.names),
                    "baselines": len(ingest.pairs), "integrations": ingest.n_time,
                    "channels": len(ingest.freqs_hz), "lmax": cfg.mmode.lmax}
    return out


def format_cluster_plan(res):
    """The cluster plan as a table: per stage tasks, task memory, worker, job shape and time; then totals."""
    node = res["node"]
    rows = [f"nodes of {node['cores']} cores, {node['memory_gb']:.1f} GB ({node['source']}"
            + (f", partition {node['partition']}" if node["partition"] else "")
            + (f", {node['available']} available" if node["available"] else "") + f"): planned on {res['nodes']}"]
    if res["settings"]:
        rows.append("split to fit a node: " + ", ".join(f"{k}={v}" for k, v in res["settings"].items()))
    rows.append(f"{'stage':12s} {'tasks':>6s} {'task GB':>8s} {'worker':>13s} {'job (per node)':>27s} "
                f"{'jobs':>5s} {'walltime':>9s} {'time':>9s}")
    for r in res["stages"]:
        j = res["jobs"][r["stage"]]
        worker = f"{r['worker_cores']}c {r['worker_memory_gb']:.1f}GB"
        job = f"{j['cores']}c {j['memory']} x{j['processes']}"
        big = "  " + "; ".join((["larger workers"] if r["worker_cores"] > 1 else []) + r["notes"])
        rows.append(f"{r['stage']:12s} {r['tasks']:6d} {r['task_gb']:8.2f} {worker:>13s} {job:>27s} "
                    f"{j['count']:5d} {j['walltime']:>9s} {duration(stage_seconds(r, res['nodes'])):>9s}{big}".rstrip())
    if len({r["worker_cores"] for r in res["stages"]}) > 1:
        rows.append("a stage of smaller workers than the running jobs' runs on those (no queue wait; more of them "
                    "where its own jobs hold more cores), one of larger workers replaces them: docs/clusters.md")
    rows.append(f"total: {res['nodes']} nodes, ~{duration(res['wall_s'])} wall ({res['node_hours']:.0f} node-hours); "
                f"a node holds at most {res['node_memory_gb']:.1f} GB of its {node['memory_gb']:.1f} GB; "
                f"{res['core_gflops']:.0f} SGEMM GFLOP/s per core")
    if "configured_worker_gb" in res:
        big = res["too_large_for_configured"]
        rows.append(f"the workflow's cluster.jobqueue: workers of {res['configured_worker_gb']:.1f} GB, "
                    + (f"too small for {', '.join(big)}: ask for the jobs above" if big else
                       "enough for every stage's task"))
    free = res["free_disk_gb"]
    rows.append(f"disk: {res['store_gb']:.1f} GB of stores live at the peak on the shared file system, "
                f"{res['store_files']:,} files written (chunks of at most {res['largest_chunk_mb']:.0f} MB; "
                "docs/clusters.md, shared file systems) ("
                + (f"{free:.1f} GB free where run.directory will be)" if free >= res["store_gb"] else
                   f"only {free:.1f} GB free where run.directory will be: mmflow run refuses it there)"))
    return "\n".join(rows)
