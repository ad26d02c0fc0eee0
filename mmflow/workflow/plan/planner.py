"""``mmflow plan``: what a run will need, per stage, before any work.

For every enabled stage the plan gives the number of tasks, the memory of its largest task, the
bytes of the stores it writes and a time estimate. Each comes from a model of the stage's work
(each stage's cost model, ``stages/<name>/cost.py``:
:func:`stage_work`): the task's working set ``W`` (bytes of the arrays a task holds: its time
chunk of visibilities, its baseline chunk over the day, its Gram accumulators, its m block) and
its work units ``U`` (visibility-samples x sources, baselines x sum_m (lmax_b - m + 1)^2, ...),
and from per-stage constants fitted to measured runs (:mod:`mmflow.workflow.plan.fit`, kept in
``plan/costs.json`` beside this module)::

    task memory  = a_s W + b_s                      (bytes above the worker's baseline)
    task seconds = (c_s U + d_s) * peak_ref / peak  (peak: this machine's SGEMM GFLOP/s now)

Store sizes are the declared stores' uncompressed bytes (:attr:`mmflow.io.stores.StoreSpec.nbytes`
of the same :mod:`mmflow.io.run_stores` declarations the stages create), an upper bound of the
disk they take (zarr compresses noise-like data by a few percent only). The disk a run needs is
the peak of its live stores (:func:`live_stores`): stages run in order, each adds its stores, and
an intermediate goes once its last reader has finished (:meth:`mmflow.workflow.pipeline.Pipeline.released`),
and so does a large array of a kept store (:meth:`mmflow.workflow.pipeline.Pipeline.released_arrays`:
:func:`run_live_stores`).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mmflow.conventions import complex_dtype
from mmflow.errors import InputError
from mmflow.imaging.maps import default_nside
from mmflow.io.run_stores import RELEASED_ARRAYS, RELEASED_BY_CHUNK, handle_of
from mmflow.machine import gemm_gflops
from mmflow.paths import expand_path
from mmflow.workflow.engine.context import build_telescope
from mmflow.workflow.engine.ingest_plan import ingest_plan
from mmflow.workflow.engine.geometry import mmax_of, n_bins_of, n_integrations
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.plan.work import Geometry, transfer_plan

COSTS_FILE = Path(__file__).with_name("costs.json")
#: A worker process's resident memory before any task (interpreter, numpy, dask, zarr, pyuvdata, the stages;
#: a local worker also numba's runtime and the imaging kernels: mmflow.workflow.engine.worker_start; measured 0.19 GB).
WORKER_BASE_BYTES = 0.35e9


@dataclass
class StageEstimate:
    """One stage's plan: tasks, the largest task's working set and work, stores and estimates."""

    stage: str
    tasks: int
    working_set_bytes: float
    units_per_task: float
    store_bytes: int
    stores: dict = field(default_factory=dict)  # {store: bytes} of the stores it writes
    task_bytes: float = 0.0  # predicted peak memory of the largest task above the worker baseline
    seconds: float = 0.0  # predicted wall time of the stage on the cluster
    notes: list = field(default_factory=list)
    arrays: dict = field(default_factory=dict)  # {store: {array: bytes}} of the arrays it writes that can go alone
    channels: dict = field(default_factory=dict)  # {store: [bytes of each channel]} of the stores it writes
    store_files: int = 0  # files of its stores with every chunk written (StoreSpec.n_files)
    largest_chunk_bytes: int = 0  # its stores' largest chunk, uncompressed


def stage_work(stage, g, cfg):
    """The :class:`mmflow.workflow.plan.work.Work` of one stage: ``(tasks, W, U, stores)``, from its own
    cost model (``mmflow/workflow/stages/<stage>/cost.py``)."""
    return PIPELINE.stage(stage).cost.work(g, cfg)


def load_costs(path=COSTS_FILE):
    """The per-stage constants ``{stage: {a, b, c, d}}`` and the ``sgemm_gflops`` they were fitted at."""
    return json.loads(Path(path).read_text())


def estimate(stage, g, cfg, costs, peak_gflops, workers, total_gflops=None):
    """The :class:`StageEstimate` of one stage on ``workers`` concurrent task slots, its tasks timed at
    the SGEMM peak ``peak_gflops`` and its stage-wide sums (a :attr:`Cost.seconds` hook's) at
    ``total_gflops`` (default: the same; a cluster's is all its nodes')."""
    cost = PIPELINE.stage(stage).cost
    tasks, w, u, specs = cost.work(g, cfg)
    k = costs["stages"].get(stage)
    est = StageEstimate(stage, tasks, w, u, int(sum(s.nbytes for s in specs)), {s.path: s.nbytes for s in specs},
                        arrays={s.path: releasable_bytes(s) for s in specs if s.path in RELEASED_ARRAYS},
                        channels={s.path: channel_bytes(s, g.n_freq) for s in specs},
                        store_files=sum(s.n_files for s in specs),
                        largest_chunk_bytes=max((s.largest_chunk_bytes for s in specs), default=0))
    if k is None and cost.seconds is None:
        est.notes.append("no fitted constants: memory = working set, time unknown")
        est.task_bytes = w
        return est
    if k is None:  # a stage that counts its own time from its work (the stokes stage), its memory its working set
        est.notes.append("no fitted constants: memory = working set, time counted from the work")
        k = {"a": 1.0, "b": 0.0, "c": 0.0, "d": 0.0}
    if cost.notes is not None:
        est.notes.extend(cost.notes(g, cfg, total_gflops or peak_gflops))
    est.task_bytes = k["a"] * w + k["b"]
    per_task = task_seconds(k, u, costs, peak_gflops)
    if cost.seconds is not None:
        est.seconds = cost.seconds(g, cfg, per_task, workers, total_gflops or peak_gflops)
    else:
        est.seconds = per_task * math.ceil(tasks / max(workers, 1))
    return est


def live_stores(writes, released):
    """The peak of the live stores of stages run in order: ``(peak bytes, the stage at which it is reached,
    {store: bytes} left at the end)``.

    ``writes``: ``[(stage, {store: bytes})]`` in run order. Each stage adds the stores it writes while the
    stores before it are still there; after it, the intermediates it was the last reader of go
    (``released``: ``{store: stage}``, :meth:`mmflow.workflow.pipeline.Pipeline.released`)::

        live(s) = sum of the stores written by stages <= s, less those released after a stage < s
        peak    = max over s of live(s)
    """
    return live_steps([(stage, stores, [u for u, after in released.items() if after == stage])
                       for stage, stores in writes])


def live_steps(steps):
    """:func:`live_stores` of steps ``[(label, {unit: bytes}, [units released after it])]``: a unit is a store,
    an array of one (``vis.zarr/vis``) or a channel's group (``partials.zarr/f0``); releasing a store releases
    its units too."""
    live, peak, at = {}, 0, None
    for label, units, gone in steps:
        live.update(units)
        if sum(live.values()) > peak:
            peak, at = sum(live.values()), label
        for u in gone:
            for k in [k for k in live if k == u or k.startswith(u + "/")]:
                live.pop(k)
    return peak, at, live


def releasable_bytes(spec):
    """``{array: bytes}`` of the arrays of a store's spec that can be released alone
    (:data:`mmflow.io.run_stores.RELEASED_ARRAYS`; a family's arrays summed under its attribute)."""
    out = {}
    for a in spec.arrays:
        attr = handle_of(spec.path, a.name)
        if attr in RELEASED_ARRAYS[spec.path]:
            out[attr] = out.get(attr, 0) + _bytes(a)
    return out


def channel_bytes(spec, n_freq):
    """The bytes of a store's spec per channel: its arrays of group ``f{F}`` in channel ``F``, the others
    (one channel per chunk along their ``freq`` axis) split evenly."""
    shared = sum(_bytes(a) for a in spec.arrays if not a.name.startswith("f")) / max(n_freq, 1)
    return [int(sum(_bytes(a) for a in spec.arrays if a.name.startswith(f"f{f}/")) + shared) for f in range(n_freq)]


def _bytes(a):
    return int(np.prod(a.shape, dtype=float) * np.dtype(a.dtype).itemsize)


def run_live_stores(writes, cfg, tasks=None, slots=1):
    """:func:`live_steps` of a run: ``writes`` ``[(stage, {store: bytes}, {store: {array: bytes}}, {store:
    [bytes per channel]})]`` in run order. The arrays that go alone
    (:meth:`mmflow.workflow.pipeline.Pipeline.released_arrays`) are units of their own (``vis.zarr/vis``)
    beside the rest of their store; a stage run channel by channel after the one before it
    (``Stage.by_channel_after``, :mod:`mmflow.workflow.engine.channels`) alternates with it, channel ``F`` of
    the first then of the second, the first's group ``f{F}`` of a store the second is the last reader of
    released after it. A stage whose finished tasks release the chunks they alone read
    (:data:`mmflow.io.run_stores.RELEASED_BY_CHUNK`: mmodes, the visibilities' baseline chunks) runs in waves of
    ``slots`` (tasks at once, or ``{stage: slots}``) of its ``tasks`` (``{stage: tasks}``; without, all at
    once): each wave writes its share of the stage's stores, then releases its share of those arrays
    (:func:`_task_wave_steps`). Returns ``(peak bytes,
    step, {store: bytes} left at the end)``."""
    released = {**PIPELINE.released(cfg), **PIPELINE.released_arrays(cfg)}
    after = {}
    for unit, stage in released.items():
        after.setdefault(stage, []).append(unit)
    steps, k = [], 0
    while k < len(writes):
        stage, stores, arrays, channels = writes[k]
        nxt = writes[k + 1] if k + 1 < len(writes) else None
        if nxt is not None and PIPELINE.stage(nxt[0]).by_channel_after == stage:
            steps += _by_channel_steps(writes[k], nxt, released, after)
            k += 2
            continue
        u = dict(stores)
        for store, per in arrays.items():
            for attr, nbytes in per.items():
                if f"{store}/{attr}" in released:
                    u[f"{store}/{attr}"] = nbytes
                    u[store] -= nbytes
        chunked = [x for x in after.get(stage, []) if x in by_chunk(cfg)]
        if tasks and tasks.get(stage, 1) > 1 and chunked:
            n = slots.get(stage, 1) if isinstance(slots, dict) else slots
            steps += _task_wave_steps(stage, u, chunked, steps, tasks[stage], n, after.get(stage, []))
        else:
            steps.append((stage, u, after.get(stage, [])))
        k += 1
    peak, at, kept = live_steps(steps)
    by_store = {}
    for unit, nbytes in kept.items():
        by_store[unit.split("/", 1)[0]] = by_store.get(unit.split("/", 1)[0], 0) + nbytes
    return peak, at, by_store


def by_chunk(cfg):
    """The released arrays (``vis.zarr/vis``) that go a chunk at a time as the tasks of the stage after which
    they are released finish (:data:`mmflow.io.run_stores.RELEASED_BY_CHUNK`, ``Stage.task_chunks``)."""
    out = []
    for unit, stage in PIPELINE.released_arrays(cfg).items():
        store, _, array = unit.partition("/")
        dim, _, arrays = RELEASED_BY_CHUNK.get(store, (None, None, ()))
        if array in arrays and dim in PIPELINE.stage(stage).task_chunks:
            out.append(unit)
    return out


def _task_wave_steps(stage, units, chunked, steps, n_tasks, slots, gone):
    """The steps of a stage whose tasks release the chunks they alone read (:func:`run_live_stores`): waves of
    ``slots`` tasks, wave ``j`` adding its share ``t_j / n`` of the stage's ``units`` (as ``unit/w{j}``) while
    the ``chunked`` arrays written before hold what the waves before it left::

        live(j) = before + sum_chunked B (1 - T_{j-1} / n) + sum_units U T_j / n   (T_j: tasks of waves <= j)

    the chunked arrays' bytes ``B`` from the steps before; ``gone`` released after the last wave."""
    size = {}
    for _, u, _ in steps:
        size.update({x: v for x, v in u.items() if x in chunked})
    waves = [min(slots, n_tasks - s) for s in range(0, n_tasks, max(slots, 1))]
    out, done = [], 0
    for j, t in enumerate(waves):
        left = {x: v * (1 - done / n_tasks) for x, v in size.items()}
        out.append((stage, {**left, **{f"{x}/w{j}": v * t / n_tasks for x, v in units.items()}},
                    gone if j == len(waves) - 1 else []))
        done += t
    return out


def _by_channel_steps(first, second, released, after):
    """The steps of two stages run channel by channel (:func:`run_live_stores`)."""
    (a, _, _, a_ch), (b, _, _, b_ch) = first, second
    n = max(len(v) for v in (*a_ch.values(), *b_ch.values()))
    steps = []
    for f in range(n):
        last = f == n - 1
        gone = [f"{s}/f{f}" for s in a_ch if released.get(s) == b]
        steps.append((a if last else f"{a} (channel {f + 1} of {n})", {f"{s}/f{f}": v[f] for s, v in a_ch.items()},
                      []))
        # what goes after the first stage goes once both are complete (the runner's releases after a stage)
        steps.append((b if last else f"{b} (channel {f + 1} of {n})", {f"{s}/f{f}": v[f] for s, v in b_ch.items()},
                      gone + (after.get(a, []) + after.get(b, []) if last else [])))
    return steps


def task_seconds(k, units, costs, peak_gflops):
    """Seconds of a task of ``units`` work by a stage's constants ``k``, at the SGEMM peak ``peak_gflops``."""
    return (k["c"] * units + k["d"]) * costs["sgemm_gflops"] / peak_gflops


def task_threads(cfg):
    """The threads each task's kernels will run on, as :func:`mmflow.threads.n_threads` gives them in the
    run's workers: ``MMFLOW_THREADS`` where set; else the usable cores of this machine for the synchronous
    scheduler, and their share per worker thread for a local cluster (``cores // (n_workers x
    threads_per_worker)``); one on a job queue or a cluster at an address (a job's cores are its worker
    threads, :mod:`mmflow.workflow.engine.pools`; a stage whose task needs a ``k``-core worker is planned at
    ``k`` threads, :func:`mmflow.workflow.plan.jobs.stage_rows`)."""
    from mmflow.threads import cores_per_thread  # deferred: threadpoolctl and scipy's BLAS

    c = cfg.cluster
    if c.kind == "synchronous":
        return cores_per_thread()
    if c.kind == "local":  # mmflow's local cluster sets MMFLOW_WORKERS_PER_HOST to its n_workers
        return cores_per_thread(c.threads_per_worker, c.n_workers)
    return cores_per_thread() if os.environ.get("MMFLOW_THREADS") else 1  # a job's cores are its worker threads


def geometry(cfg, ingest=None, threads=None):
    """The :class:`Geometry` of a configuration: from the telescope for a simulation, from the
    files' metadata (no visibilities read) for ingested data, or from ``ingest`` (an object with the
    ingest plan's ``layout``, ``pairs``, ``n_time``, ``pols`` and ``freqs_hz``: a record's copy,
    :func:`mmflow.workflow.plan.fit.record_ingest`) where the files are not at hand. ``threads``: each
    task's threads (a record's, as measured), else :func:`task_threads`."""
    mm = cfg.mmode
    mmax = mmax_of(cfg)
    itemsize = complex_dtype(cfg.transfer.dtype).itemsize
    if cfg.source == "simulate":
        tel = build_telescope(cfg)
        n_time = n_integrations(cfg)
        n_pol = 2 if cfg.corrupt.enabled else 1
        freqs = tel.freqs_hz
        n_bins = n_bins_of(cfg, cfg.observation.integration_s)
    else:
        plan = ingest_plan(cfg) if ingest is None else ingest  # a record's copy of the files' plan
        tel = build_telescope(cfg, plan)  # the files' array, channels and baselines, not the config's telescope
        tel.pairs = np.asarray(plan.pairs)
        n_time, n_pol, freqs = plan.n_time, len(plan.pols), np.asarray(plan.freqs_hz)
        tau = getattr(plan, "integration_s", None)  # a record's copy may lack it: a day of its integrations
        n_bins = n_bins_of(cfg, tau) if tau else cfg.mmode.n_bins or n_time
    n_bl = len(tel.antenna_pairs())
    tplans = [transfer_plan(tel, float(f), cfg, mmax) for f in freqs]
    nside = cfg.products.nside or default_nside(mm.lmax)
    return Geometry(n_time=n_time, n_ant=tel.n_ant, n_bl=n_bl, n_freq=len(freqs), n_pol=n_pol, lmax=mm.lmax,
                    mmax=mmax, m_block=cfg.transfer.m_block, n_split=len(mm.splits), mmode_chunk=mm.baseline_chunk,
                    gram_itemsize=itemsize, transfer_units=tuple(p[0] for p in tplans),
                    transfer_workspace=max(p[2] for p in tplans),
                    transfer_read=max(p[1] for p in tplans), npix=12 * nside ** 2, n_bins=n_bins,
                    task_threads=threads or task_threads(cfg), tel=tel,
                    freqs_hz=tuple(float(f) for f in freqs))


def plan(cfg, costs=None, peak_gflops=None, ingest=None):
    """Per enabled stage a :class:`StageEstimate`, and the run's totals against its limits.

    Returns
    -------
    dict
        ``stages`` (list of estimates as dicts), ``task_slots`` (tasks running at once, by which each
        stage's per-task time is multiplied), ``total_store_gb`` (every store written), ``peak_store_gb``
        and ``peak_stage`` (the live stores' peak, :func:`live_stores`), ``kept_stores`` (``{store: GB}``
        left at the end), ``largest_task`` (stage and GB),
        ``worker_memory_gb`` (the cluster's per-worker limit, or None) and ``free_disk_gb`` where
        the run directory will be. ``ingest``: as in :func:`geometry`.
    """
    costs = costs or load_costs()
    if peak_gflops is None:
        peak_gflops = gemm_gflops(np.float32, n=768)
    g = geometry(cfg, ingest)
    workers = cfg.cluster.n_workers * cfg.cluster.threads_per_worker if cfg.cluster.kind != "synchronous" else 1
    ests = [estimate(st.name, g, cfg, costs, peak_gflops, workers) for st in PIPELINE
            if st.enabled(cfg) and st.task is not None]
    largest = max(ests, key=lambda e: e.task_bytes)
    peak, at, kept = run_live_stores([(e.stage, e.stores, e.arrays, e.channels) for e in ests], cfg,
                                     {e.stage: e.tasks for e in ests}, workers)
    return {"stages": [vars(e) for e in ests], "sgemm_gflops": peak_gflops, "task_slots": workers,
            "total_store_gb": sum(e.store_bytes for e in ests) / 1e9, "peak_store_gb": peak / 1e9,
            "peak_stage": at, "kept_stores": {k: v / 1e9 for k, v in kept.items()},
            "largest_task": {"stage": largest.stage, "gb": (largest.task_bytes + WORKER_BASE_BYTES) / 1e9},
            "worker_memory_gb": worker_memory_gb(cfg), "free_disk_gb": free_disk_gb(cfg.run.directory),
            "total_seconds": sum(e.seconds for e in ests)}


def worker_memory_gb(cfg):
    """A local worker's memory limit in GB (dask's 'auto' splits the machine among workers);
    None where the cluster is not local (its limit is the scheduler's business)."""
    from dask.utils import parse_bytes  # deferred: dask takes 0.3-0.8 s to import; `mmflow status` loads this

    c = cfg.cluster
    if c.kind not in ("local", "synchronous"):
        return None
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if c.kind == "synchronous" or c.memory_limit == "auto":
        return total / (1 if c.kind == "synchronous" else c.n_workers) / 1e9
    try:
        frac = float(c.memory_limit)
        return frac * total / 1e9
    except ValueError:
        return parse_bytes(c.memory_limit) / 1e9


def free_disk_gb(run_directory):
    """Free bytes (GB) on the file system that holds (or will hold) the run directory."""
    p = Path(expand_path(run_directory)).absolute()
    while not p.exists():
        p = p.parent
    st = os.statvfs(p)
    return st.f_bavail * st.f_frsize / 1e9


def format_plan(res):
    """The plan as a table: per stage tasks, largest task (GB), stores (GB) and time; then totals."""
    rows = [f"{'stage':12s} {'tasks':>7s} {'task GB':>8s} {'store GB':>9s} {'time':>9s}"]
    for e in res["stages"]:
        t = duration(e["seconds"]) if e["seconds"] else "?"
        rows.append(f"{e['stage']:12s} {e['tasks']:7d} {(e['task_bytes'] + WORKER_BASE_BYTES) / 1e9:8.2f} "
                    f"{e['store_bytes'] / 1e9:9.3f} {t:>9s}" + (f"  ({'; '.join(e['notes'])})" if e["notes"] else ""))
    lt, wm = res["largest_task"], res["worker_memory_gb"]
    kept = res["kept_stores"]
    rows.append(f"stores: {res['peak_store_gb']:.3f} GB live at the peak (after {res['peak_stage']}; "
                f"{res['free_disk_gb']:.1f} GB free), {res['total_store_gb']:.3f} GB written; kept at the end "
                f"{sum(kept.values()):.3f} GB: {', '.join(kept)}")
    rows.append(f"total: ~{duration(res['total_seconds'])} at {res['sgemm_gflops']:.0f} SGEMM GFLOP/s")
    rows.append(f"largest task: {lt['stage']} {lt['gb']:.2f} GB (with a worker's baseline)"
                + (f" against {wm:.2f} GB per worker" if wm else ""))
    return "\n".join(rows)


def duration(s):
    """Seconds as text: ``45 s``, ``3.5 min``, ``2.1 h``."""
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min" if s < 7200 else f"{s / 3600:.1f} h"


def check_fits(cfg, worker_limit_gb, stage_names, free_disk=None, existing_bytes=0):
    """Refuse, before any work, a run whose largest task exceeds a worker's memory or whose stores
    exceed the free disk at their peak (:func:`live_stores`): an :class:`mmflow.errors.InputError` naming
    the stage, the estimate, the limit and the setting that fixes it. ``existing_bytes``: what the run's
    stores hold already."""
    g = geometry(cfg)
    costs = load_costs()
    workers = 1
    ests = [estimate(n, g, cfg, costs, costs["sgemm_gflops"], workers) for n in stage_names]
    if worker_limit_gb:
        for e in ests:
            need = (e.task_bytes + WORKER_BASE_BYTES) / 1e9
            if need > worker_limit_gb:
                raise InputError("workflow", f"stage {e.stage}", f"its largest task needs ~{need:.2f} GB "
                                 f"(`mmflow plan`), more than the {worker_limit_gb:.2f} GB a task has on a worker "
                                 "(its memory limit over the tasks it runs at once, its threads)",
                                 f"{PIPELINE.stage(e.stage).cost.shrink_setting(cfg)}, or more memory per worker "
                                 "(fewer cluster.n_workers, a larger cluster.memory_limit, fewer threads a worker)")
    slots = cfg.cluster.n_workers * cfg.cluster.threads_per_worker if cfg.cluster.kind != "synchronous" else 1
    peak, at, _ = run_live_stores([(e.stage, e.stores, e.arrays, e.channels) for e in ests], cfg,
                                  {e.stage: e.tasks for e in ests}, slots)
    disk = peak - existing_bytes
    free = free_disk_gb(cfg.run.directory) if free_disk is None else free_disk
    if disk / 1e9 > free:
        big = max(ests, key=lambda e: e.store_bytes)
        raise InputError(str(cfg.run.directory), "run.directory", f"the stores need up to {disk / 1e9:.2f} GB "
                         f"at once (`mmflow plan`: the live stores' peak, after {at}; {big.stage} "
                         f"{big.store_bytes / 1e9:.2f} GB), more than the {free:.2f} GB free there",
                         f"{PIPELINE.stage(big.stage).cost.disk_shrink_setting(cfg)}, free disk space, or set "
                         "run.directory on a larger file system")
    return ests
