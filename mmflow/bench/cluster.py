"""``mmflow bench cluster``: the workflow on 1, 2 and 3 SLURM nodes, each a network namespace.

A real SLURM 22.05 cluster of three nodes of 2 CPUs and 3000 MB (:mod:`mmflow.bench.netns_slurm`: each
node a network namespace and hostname on a bridge of its own; every process stopped by PID, the
namespaces and bridge deleted at the end, also on failure) runs the same workflow with one worker job
per node (``--exclusive``) on 1, 2 and 3 nodes; a synchronous run in process is the reference. The
workers reach the driver's scheduler over the bridge (``cluster.interface``), the run directory is the
shared filesystem. Per run the JSON gives:

* ``wall_s`` (the run, from the workers' arrival to its end; the job start is ``workers_up_s``),
  ``tasks`` and ``task_s`` (mmflow's in-task seconds, from the run's ``summary.json``);
* ``overhead_fraction``: ``(wall_s x workers - task_s) / task_s``, every second a worker slot spent
  outside a task (driver-side planning and finalisation, stage barriers, idle slots when a stage has
  fewer tasks than workers, dask) over task time: an upper bound of the scheduling overhead, and
  ``overhead_per_task_s``, the same time per task;
* from dask's task stream (``startstops``): ``dask_compute_s`` (dask's compute time of the tasks),
  ``wrapper_fraction`` (``dask_compute_s / task_s - 1``: the task wrapper's markers and checks) and
  ``dispatch_gap_s`` (median and sum of the gaps between consecutive tasks of a stage on one worker:
  the scheduler's per-task latency while a worker has work queued);
* ``bytes_between_workers``: bytes a worker sent to another worker (the workers'
  ``transfer_outgoing_log``, requests from worker addresses) and the dependency transfers in the task
  stream; ``bytes_to_driver`` (task results the driver gathered) beside ``store_bytes`` (what the
  stages wrote to the shared filesystem);
* ``identical``: every array of the run's stores bit-identical to the reference run's.

Beside them: ``projection``, :func:`mmflow.workflow.plan.jobs.array_projection` of the 352-antenna array
on 8 and 64 nodes of 32 cores and 128 GB, and ``overhead_at_array_task_sizes``: the measured per-task
overhead (dispatch gap and wrapper) against the array's planned task seconds, where the < 2 % target
applies (the reduced workflow's tasks last milliseconds to a second: a fixed per-task cost is a large
fraction of them); ``no_worker_computing_s``: the run's wall time with no task running on any worker
(the driver's planning and finalisation between stages), set per stage against the array's planned
wall time (``stage_barriers_fraction_of_wall``); ``sgemm_gflops``, the machine's SGEMM peak measured in the same run.

Needs root and network namespaces (and slurm-wlm and munge, installed with apt-get where they can
be): elsewhere the JSON says why it did not run. All nodes share this machine's CPUs: the
multi-node runs measure the cost of spreading, not a speed-up. ``--quick``: the demo at the test
suite's small settings (lmax 24, one channel); without it the demo at lmax 64.
"""
from __future__ import annotations

import hashlib
import os
import socket
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from mmflow.environ import restored_environ
from mmflow.bench.netns_slurm import NamespacedSlurm, unavailable
from mmflow.io.run_stores import STORES
from mmflow.machine import gemm_gflops, machine

DEMO = Path(__file__).resolve().parents[2] / "workflows" / "demo.yaml"
#: the demo at the test suite's small settings (tests/workflow_helpers.py SMALL, cluster aside)
QUICK = ["telescope.radius_m=20", "observation.freqs_mhz=[40.0]", "observation.integration_s=344.6563620",
         "sky.diffuse=true", "sky.diffuse_lmax=16", "sky.quad_oversample=16", "mmode.lmax=24",
         "mmode.baseline_chunk=64", "transfer.baseline_chunk=32", "transfer.m_block=8", "products.nside=32",
         "products.flux_scale=false"]
#: the demo at lmax 64, one channel
FULL = ["observation.freqs_mhz=[40.0]", "mmode.lmax=64", "products.flux_scale=false"]
PAPER = DEMO.parent / "paper-scale.yaml"
#: a sidereal day (s)
SIDEREAL_DAY_S = 86164.0905
#: workflows/paper-scale.yaml reduced to a minute of CPU: 64 antennas (2,080 baselines), 256 integrations
#: over the sidereal day (calibration solutions of 16), lmax 100, the compact sources only, 2 CLEAN cycles,
#: no PNGs. Its simulate task plans ~0.55 GB and every other stage's less than 0.51 GB: on nodes of 2 CPUs
#: and 1500 MB (1 GiB to a job) the plan gives simulate workers of 2 cores and the rest workers of one
PAPER_REDUCED = ["telescope.max_antennas=64", f"observation.integration_s={SIDEREAL_DAY_S / 256:.7f}",
                 f"calibrate.solint_s={16 * SIDEREAL_DAY_S / 256:.4f}", "mmode.lmax=100", "sky.diffuse=false",
                 "clean.max_cycles=2", "products.png=false"]
ARRAY = DEMO.parent / "ovro-lwa-stage3.yaml"
#: workflows/ovro-lwa-stage3.yaml (the 352-antenna array, 61,776 baselines) reduced to fit a 2-core / 24 GB
#: machine in minutes: simulated instead of read from its files, its lowest channel (41.76 MHz), 128
#: integrations over the sidereal day, lmax 50 (the longest baselines need ~2300: this is a memory check, not
#: a map), no diffuse sky, maps at nside 64; its calibration, peeling, terrestrial filter and splits as the
#: workflow's. The transfer's Fourier stage grows as the longest fringes squared, not with lmax: at its 73.152
#: MHz channel the same run's transfer took 969 s of its 1177 (synchronous, on this VM), at 41.76 MHz ~3x less
ARRAY_REDUCED = ["source=simulate", "observation.freqs_mhz=[41.76]",
                 f"observation.integration_s={SIDEREAL_DAY_S / 128:.7f}", "mmode.lmax=50", "sky.diffuse=false",
                 "products.nside=64"]
#: ``--workflow``: name -> (file, overrides, its --quick overrides, what it is)
WORKFLOWS = {
    "demo": (DEMO, None, None, "the demo at lmax 64, one channel (--quick: the test suite's small demo)"),
    "paper": (PAPER, PAPER_REDUCED, PAPER_REDUCED, "workflows/paper-scale.yaml reduced: 64 antennas, 256 "
              "integrations, lmax 100 (bench.cluster.PAPER_REDUCED)"),
    "array": (ARRAY, ARRAY_REDUCED, [*ARRAY_REDUCED, "telescope.max_antennas=64"],
              "workflows/ovro-lwa-stage3.yaml reduced: 352 antennas (--quick: 64), one channel, 128 integrations, "
              "lmax 50 (bench.cluster.ARRAY_REDUCED)"),
}
#: the plan's task memory against the largest task's traced peak: the bound issue 38 sets (and the pipeline test's)
TRACED_TOLERANCE = 0.25
#: stores whose arrays are compared bit for bit with the reference run
COMPARED = (STORES.vis, STORES.mmodes, STORES.normal, STORES.alm, STORES.stokes)
NODES = (1, 2, 3)


def store_digests(run_dir):
    """``{store/array: sha256 of its bytes, dtype and shape}`` of every array of the run's :data:`COMPARED` stores."""
    import zarr  # deferred: zarr (~1 s)

    out = {}
    for store in COMPARED:
        path = Path(run_dir) / store
        if not path.exists():
            continue

        def walk(group, prefix):
            for name, arr in group.arrays():
                a = np.ascontiguousarray(arr[:])
                h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
                h.update(a.view(np.uint8).reshape(-1) if a.size else b"")
                out[f"{prefix}/{name}"] = h.hexdigest()
            for name, sub in group.groups():
                walk(sub, f"{prefix}/{name}")

        walk(zarr.open_group(str(path), mode="r"), store)
    return out


def _totals(summaries):
    tasks = sum(s.get("tasks_run", 0) for s in summaries.values())
    task_s = sum(s.get("task_s", 0.0) for s in summaries.values())
    stores = sum(s.get("bytes_written", 0) or 0 for s in summaries.values())
    return tasks, task_s, stores


def _outgoing(dask_worker=None):
    """A worker's outgoing transfers: ``[(requester, bytes), ...]`` (run on every worker)."""
    return [(e["who"], int(e["total"])) for e in dask_worker.transfer_outgoing_log]


def stream_figures(stream):
    """Figures of dask's task stream: compute seconds, dependency transfers, dispatch gaps."""
    compute, transfer_bytes, transfers = 0.0, 0, 0
    by_slot = {}  # (worker, thread, stage) -> [(start, stop)]
    for rec in stream:
        stage = str(rec.get("key", "")).split("-")[0]
        for ss in rec.get("startstops", ()):
            if ss["action"] == "compute":
                compute += ss["stop"] - ss["start"]
                by_slot.setdefault((rec.get("worker"), rec.get("thread"), stage), []).append((ss["start"], ss["stop"]))
            elif ss["action"] == "transfer":
                transfers += 1
                transfer_bytes += int(rec.get("nbytes") or 0)
    spans_all = sorted(sp for spans in by_slot.values() for sp in spans)
    busy, end = 0.0, None  # the union of the compute intervals: some worker computing
    for a, b in spans_all:
        if end is None or a > end:
            busy += b - a
            end = b
        elif b > end:
            busy += b - end
            end = b
    gaps = []
    for spans in by_slot.values():
        spans.sort()
        gaps += [max(0.0, b[0] - a[1]) for a, b in zip(spans, spans[1:])]
    return {"records": len(stream), "dask_compute_s": round(compute, 3),
            "any_worker_computing_s": round(busy, 3), "dependency_transfers": transfers,
            "dependency_transfer_bytes": transfer_bytes,
            "dispatch_gap_s": {"median": round(statistics.median(gaps), 5) if gaps else None,
                               "sum": round(sum(gaps), 3), "count": len(gaps)}}


def plan_vs_traced(cfg, run_dir, peak_gflops):
    """Per stage the plan's task memory (:func:`mmflow.workflow.plan.planner.plan`) against the largest
    traced peak of its tasks (``traced_peak_bytes``, recorded where the workers trace their allocations:
    ``PYTHONTRACEMALLOC``), as ``tests/acceptance/test_plan_traced.py`` compares them; ``within`` is
    :data:`TRACED_TOLERANCE`.

    A traced peak is its worker process's: only the tasks that recorded running alone in their worker
    (``tasks_at_once`` 1, :class:`mmflow.workflow.engine.resources.TasksAtOnce`; a run from before the count
    records none) are compared. Where none did, the stage's entry says how many shared the peaks
    (``tasks_at_once``, when recorded) and ``within`` is None: that peak is not one task's. The largest task
    that ran alone need not be the stage's largest (``tasks_alone`` of ``tasks`` say how many were compared)."""
    from mmflow.workflow.engine.rundir import RunDir  # deferred: as load_config in run_on_slurm
    from mmflow.workflow.plan.planner import plan

    run = RunDir(run_dir)
    out = {}
    for e in plan(cfg, peak_gflops=peak_gflops)["stages"]:
        infos = [i for i in run.task_infos(e["stage"]).values() if "traced_peak_bytes" in i]
        if not infos:
            continue
        alone = [i["traced_peak_bytes"] for i in infos if i.get("tasks_at_once") == 1]
        traced = max(alone or [i["traced_peak_bytes"] for i in infos])
        ratio = e["task_bytes"] / traced
        out[e["stage"]] = {"planned_gb": round(e["task_bytes"] / 1e9, 4), "traced_gb": round(traced / 1e9, 4),
                           "planned/traced": round(ratio, 3), "tasks_alone": len(alone), "tasks": len(infos),
                           "within": abs(ratio - 1) <= TRACED_TOLERANCE if alone else None}
        if not alone:
            out[e["stage"]]["tasks_at_once"] = max((i.get("tasks_at_once", 0) for i in infos), default=0) or None
    return out


def run_on_slurm(slurm, n, overrides, directory, reference, memory="1GB", workflow=DEMO, sized=False):
    """The workflow on ``n`` nodes of ``slurm``: the run's figures. One exclusive worker job a node, of one
    core and ``memory``; or (``sized``) the jobs sized per stage from the plan on ``n`` of the nodes
    (``cluster.n_workers``; :mod:`mmflow.workflow.engine.pools`)."""
    from mmflow.workflow.config.schema import load_config  # deferred: the schema loads dask
    from mmflow.workflow.engine.cluster import open_cluster
    from mmflow.workflow.engine.passes import run_with_passes

    run_dir = Path(directory) / f"nodes{n}"
    jobs = [] if sized else [f"cluster.jobqueue={{cores: 1, memory: {memory}, walltime: '00:30:00',"
                             " job_extra_directives: ['--exclusive']}"]
    cfg = load_config(workflow, list(overrides) + [
        f"run.directory={run_dir}", "cluster.kind=slurm", f"cluster.n_workers={n}", "cluster.dashboard_address=:0",
        f"cluster.interface={slurm.bridge}", *jobs])
    logs = []
    t_submit = time.time()
    with open_cluster(cfg, log=logs.append) as client:
        if not sized:  # sized per stage: each stage's jobs are submitted as it starts (in wall_s)
            client.wait_for_workers(n, timeout=300)
        up = time.time() - t_submit
        hosts = {} if sized else client.run(socket.gethostname)
        client.get_task_stream(start=time.time())  # starts the scheduler's task-stream record
        t0 = time.time()
        summaries = run_with_passes(cfg, client, progress=False, log=logs.append)
        wall = time.time() - t0
        stream = client.get_task_stream(start=t0 - 1)
        outgoing = client.run(_outgoing)
        workers = set(outgoing)
        hosts = hosts or client.run(socket.gethostname)  # sized per stage: the last stage's workers
    tasks, task_s, stores = _totals(summaries)
    stages = sum(1 for s in summaries.values() if s.get("tasks_run"))
    between = sum(b for log in outgoing.values() for who, b in log if who in workers)
    to_driver = sum(b for log in outgoing.values() for who, b in log if who not in workers)
    st = stream_figures(stream)
    return {"nodes": n, "workers": len(hosts), "hosts": sorted(set(hosts.values())),
            "workers_up_s": round(up, 2), "wall_s": round(wall, 2), "stages": stages,
            "tasks": tasks, "task_s": round(task_s, 3),
            "overhead_fraction": round((wall * len(hosts) - task_s) / task_s, 4) if task_s else None,
            "overhead_per_task_s": round((wall * len(hosts) - task_s) / tasks, 4) if tasks else None,
            **st, "no_worker_computing_s": round(wall - st["any_worker_computing_s"], 3),
            "wrapper_fraction": round(st["dask_compute_s"] / task_s - 1, 4) if task_s else None,
            "bytes_between_workers": between, "bytes_to_driver": to_driver, "store_bytes": stores,
            "identical": None if reference is None else store_digests(run_dir) == reference,
            "pools": [line for line in logs if line.startswith("stage ")], "config": cfg}


def array_task_sizes(proj, per_task_s):
    """The per-task overhead ``per_task_s`` against the 352-antenna array's planned tasks: per stage
    and over all tasks (``sum(tasks x overhead) / sum(tasks x planned seconds)``)."""
    rows = [r for r in proj["stages"] if r["tasks"]]
    total_tasks = sum(r["tasks"] for r in rows)
    total_s = sum(r["tasks"] * r["per_task_s"] for r in rows)
    return {"per_task_overhead_s": round(per_task_s, 5), "array_tasks": total_tasks,
            "array_mean_task_s": round(total_s / total_tasks, 2) if total_tasks else None,
            "fraction": per_task_s * total_tasks / total_s if total_s else None,
            "target_fraction": 0.02,
            "per_stage": {r["stage"]: {"tasks": r["tasks"], "planned_task_s": round(r["per_task_s"], 2),
                                       "fraction": per_task_s / r["per_task_s"] if r["per_task_s"] else None}
                          for r in rows}}


def run(what="cluster", quick=False, slurm=None, nodes=NODES, directory=None, workflow="demo", node_memory_mb=3000,
        reference=True):
    """Run the benchmark; ``slurm``: a started :class:`~mmflow.bench.netns_slurm.NamespacedSlurm` of at
    least ``max(nodes)`` nodes (the tests' session cluster), else one of ``node_memory_mb`` a node is
    started here and stopped. ``workflow``: a name of :data:`WORKFLOWS`; the demo runs on one exclusive
    1-core job a node, the others on jobs sized per stage from the plan, with their workers tracing their
    allocations (``PYTHONTRACEMALLOC``) for :func:`plan_vs_traced`. ``reference=False``: no synchronous
    reference run first (the plan against the traced peaks only; each run's ``identical`` is None)."""
    path, full, small, about = WORKFLOWS[workflow]
    overrides = (QUICK if quick else FULL) if workflow == "demo" else (small if quick else full)
    sized = workflow != "demo"
    res = {"machine": machine(), "workflow": {"file": f"workflows/{path.name}", "overrides": overrides,
                                              "settings": "the test suite's small demo" if quick and not sized
                                              else about}}
    if slurm is None:
        why = unavailable()
        if why:
            return {**res, "ran": False, "why": why}
    res["sgemm_gflops"] = gemm_gflops(np.float32)
    from mmflow.workflow.config.schema import load_config  # deferred: the schema loads dask
    from mmflow.workflow.engine.passes import run_with_passes

    env = {"SLURM_CONF": None, "PYTHONTRACEMALLOC": "1" if sized else None,
           # mmflow's tasks hold no results in a worker: pausing a worker whose freed heap stays resident
           # only stalls it (the small nodes here make workers of ~1 GiB)
           "DASK_DISTRIBUTED__WORKER__MEMORY__PAUSE": "False" if sized else None}
    with (tempfile.TemporaryDirectory(prefix="mmflow-bench-cluster-", dir=directory) as root,
          restored_environ(*env)):
        if reference:
            cfg = load_config(path, list(overrides) + ["cluster.kind=synchronous", f"run.directory={root}/reference"])
            t0 = time.time()
            summaries = run_with_passes(cfg, None, progress=False, log=lambda *a: None)
            tasks, task_s, stores = _totals(summaries)
            res["reference"] = {"cluster": "synchronous, in process", "wall_s": round(time.time() - t0, 2),
                                "tasks": tasks, "task_s": round(task_s, 3), "store_bytes": stores}
            reference = store_digests(f"{root}/reference")
            res["reference"]["arrays"] = len(reference)
        else:
            res["reference"], reference = "none (--no-reference: the plan against the traced peaks only)", None
        own = slurm is None
        try:
            if own:
                slurm = NamespacedSlurm(Path(root) / "slurm", n_nodes=max(nodes), cpus=2, memory_mb=node_memory_mb,
                                        tag=f"mb{os.getpid() % 100000}")
                slurm.start()
            env["SLURM_CONF"] = str(slurm.conf)
            os.environ.update({k: v for k, v in env.items() if v is not None})
            res["slurm"] = {"nodes": len(slurm.nodes), "cpus_per_node": slurm.cpus, "memory_mb": slurm.memory_mb,
                            "started_here": own, "network": str(slurm.subnet)}
            memory = "1GB" if quick else "2GB"
            res["job"] = ("sized per stage from the plan (sinfo)" if sized else
                          {"cores": 1, "memory": memory, "exclusive": True})
            res["runs"] = [run_on_slurm(slurm, n, overrides, root, reference, memory, path, sized) for n in nodes]
            for r in res["runs"]:
                run_cfg = r.pop("config")
                if sized:
                    r["plan_vs_traced"] = plan_vs_traced(run_cfg, run_cfg.run.directory, res["sgemm_gflops"])
        finally:
            if own and slurm is not None:
                slurm.stop()
    from mmflow.workflow.plan.jobs import array_projection  # deferred: the planner's modules

    res["projection"] = array_projection((8, 64), peak_gflops=res["sgemm_gflops"])
    last = res["runs"][-1]
    gap = last["dispatch_gap_s"]["median"] or 0.0
    wrapper = max(0.0, last["dask_compute_s"] - last["task_s"]) / max(last["tasks"], 1)
    barrier = last["no_worker_computing_s"] / max(last["stages"], 1)
    n_stages = len(res["projection"]["stages"])
    res["overhead_at_array_task_sizes"] = {
        "measured_on": f"{last['nodes']} nodes", "dispatch_gap_s": gap, "wrapper_s": round(wrapper, 5),
        **array_task_sizes(res["projection"], gap + wrapper),
        # the driver's time between stages (no worker computing), once per stage of the array's plan
        "stage_barrier_s": round(barrier, 3),
        "stage_barriers_fraction_of_wall": {n: barrier * n_stages / p["wall_s"]
                                            for n, p in res["projection"]["nodes"].items()}}
    res["sgemm_gflops_after"] = gemm_gflops(np.float32)
    res["ran"] = True
    return res
