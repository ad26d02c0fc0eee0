"""Run stages in order on a dask client, resumably, under the run directory's lock.

What a run guarantees (each covered by ``tests/acceptance/test_faults.py``):

* one driver per run directory (an exclusive lock naming its holder; a killed holder's lock
  is released by the kernel);
* every stage's fingerprint comes from what it declares it reads (settings, input stores,
  input files); stale outputs are refused before any work starts, with the settings that
  changed, unless ``--force`` recomputes them; a stage none of whose tasks finished holds no
  result, and starts afresh with other settings without ``--force``;
* an error that is the input's (:class:`mmflow.errors.InputError`) is found before any work
  where a check can find it (the stages' ``check`` and ``scan``); raised in a task, it fails that
  task once (never retried, no worker traceback) and stops the run; a stage none of whose tasks
  finished leaves no store behind, and a run refused before any work leaves only its log;
* work keys come from the data and the settings, never from the cluster, and a stage is
  complete only when every key has its marker (named by :meth:`TaskKey.format`, the task
  handed :meth:`TaskKey.parse` of that name);
* inputs are checked against their producers' chunk records before they are read;
* a stage that has had no worker for ``cluster.worker_wait_s`` fails, naming the stage (SLURM/PBS:
  only while no worker job is queued or starting; a worker that cannot reach the scheduler stops
  the run with its own error, :class:`mmflow.workflow.engine.batch.JobWatch`);
* an intermediate store (:data:`mmflow.io.run_stores.RELEASED_BY_DEFAULT`, less ``run.keep``) is
  released once its writer and every enabled stage that reads it are complete with the current
  settings (:func:`mmflow.workflow.engine.release.release_finished`), the release recorded with its
  writer; a stage that has work again and reads a released store has its writer recomputed first
  (:func:`mmflow.workflow.engine.release.recompute_released`),
  bit for bit, and a resume whose remaining stages do not read it recomputes nothing;
* a stage that sums what the stage before it wrote per channel (``normal``: ``Stage.by_channel_after``)
  runs with it channel by channel, each channel's intermediates released once summed
  (:mod:`mmflow.workflow.engine.channels`).
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import replace
from importlib.metadata import PackageNotFoundError, version

import yaml
import zarr

from mmflow.allocator import keep_freed_memory, release_freed_memory
from mmflow.errors import InputError, MmflowError, StaleOutputError
from mmflow.io.stores import DamagedStoreError, verify_chunks
from mmflow.threads import blas_on_one_thread, blas_threads, n_threads
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.dashboard.board import BOARD, cluster_kind, cluster_record
from mmflow.workflow.engine.context import Context
from mmflow.workflow.engine.fingerprint import StageFingerprint, config_values, stage_file_digests
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.plan.planner import check_fits
from mmflow.workflow.engine.resources import (TasksAtOnce, current_rss_bytes, dask_worker, gb, peak_rss_bytes,
                                              reset_peak_rss, reset_traced_peak, traced_peak_bytes)
from mmflow.workflow.engine.channels import by_channel, by_channel_partner
from mmflow.workflow.engine.release import (chunk_releases, planned_keys, recompute_released, release_finished,
                                            release_task_chunks, released_here, repair_or_refuse)
from mmflow.workflow.engine.progress import Progress
from mmflow.workflow.engine.pools import TASK_SLOT
from mmflow.workflow.engine.rundir import RunDir
from mmflow.workflow.engine.task_key import TaskKey

PACKAGES = ("mmflow", "numpy", "scipy", "dask", "distributed", "zarr", "healpy", "astropy", "ducc0", "pyuvdata")


def versions():
    out = {}
    for p in PACKAGES:
        try:
            out[p] = version(p)
        except PackageNotFoundError:
            out[p] = None
    return out


#: A worker resident above this when a task starts holds earlier tasks' freed memory (no result stays in a
#: worker: tasks write stores): it is given back first (mmflow.allocator.release_freed_memory), so that a
#: task's peak is its own working set on the worker's baseline.
RELEASE_ABOVE_BYTES = 1.5e9
#: A dask worker resident above this share of its memory limit when a task ends gives its freed memory back:
#: dask pauses a worker above 80 % of its limit (``distributed.worker.memory.pause``) and it would stay paused,
#: starting no task, while that memory stays resident (small workers: jobs sized per stage from the plan)
RELEASE_ABOVE_SHARE = 0.7


def run_task(ctx, pipeline, stage_name, key):
    """Worker side: skip if marked done, else compute, write, then mark (atomically).

    ``key`` is the task's marker name (:meth:`TaskKey.format`); the stage's task gets the :class:`TaskKey`.
    """
    keep_freed_memory()  # dask workers start with a 64 kB trim threshold: every array a fresh mmap
    run = ctx.run
    run.check_holder(ctx.token)
    if run.is_done(stage_name, key):
        return {"key": key, "skipped": True}
    delay = float(os.environ.get("MMFLOW_TASK_DELAY_S", "0") or 0)
    if delay:  # a knob to slow tasks down: watch the dashboard, or test kills mid-stage
        time.sleep(delay)
    if current_rss_bytes() > RELEASE_ABOVE_BYTES:  # an earlier task's freed memory, still resident
        release_freed_memory()
    with TasksAtOnce() as at_once:  # the peaks below are the process's: one task's only where it ran alone
        reset_peak_rss()  # the worker's high-water mark from here covers this task (mmflow.workflow.engine.resources)
        rss_start = current_rss_bytes()
        traced_start = reset_traced_peak()  # None unless the process traces its allocations (tracemalloc)
        t0 = time.time()
        stage = pipeline.stage(stage_name)
        tctx = ctx.for_stage(stage).for_task(keep_handles=True)
        worker, limit = dask_worker() or (None, None)
        with blas_on_one_thread(for_good=worker is not None):  # the same bits in every executor
            info = stage.task(tctx, TaskKey.parse(key)) or {}
            info = dict(info, blas_threads=blas_threads())  # BLAS's threads in the task's kernels: one (above)
        info = dict(info, started=round(t0, 3), seconds=round(time.time() - t0, 3),
                    checksum_s=round(tctx.ledger.seconds, 4), guard_s=round(tctx.ledger.guard_seconds, 4),
                    peak_rss_gb=gb(peak_rss_bytes()),
                    rss_start_gb=gb(rss_start), threads=n_threads())
        if worker is not None:  # the worker the task was sent to, and its memory (jobs sized per stage)
            info.update(worker=worker, worker_memory_bytes=limit and int(limit))
        if traced_start is not None:
            traced = traced_peak_bytes(traced_start)
            info["traced_peak_gb"] = gb(traced)
            info["traced_peak_bytes"] = int(traced)  # exact: the GB figure of a small task is coarse
    info["tasks_at_once"] = at_once.most  # 1: the peaks are this task's alone
    run.check_holder(ctx.token)
    run.mark_done(stage_name, key, info, tctx.ledger.entries)
    if limit and current_rss_bytes() > RELEASE_ABOVE_SHARE * limit:
        release_freed_memory()
    return {"key": key, "skipped": False, **info}


def run_task_reporting_input_errors(ctx, pipeline, stage_name, key):
    """:func:`run_task` as dask workers run it: an error that is the input's (:class:`InputError` and
    its kin) comes back as the task's result, ``{"key": key, "input_error": exc}``, instead of being raised.

    Dask retries a task that raises (``retries``) and its worker logs each attempt with a traceback
    ("Compute Failed"); a bad input fails the same way every time, so it is reported once and never
    retried. The driver raises it (:func:`_gather_stage`) and stops the stage.
    """
    try:
        return run_task(ctx, pipeline, stage_name, key)
    except InputError as exc:
        return {"key": key, "input_error": exc}


def stage_fingerprints(cfg, run=None, pipeline=PIPELINE):
    """``{stage: StageFingerprint}`` of every enabled stage (None for disabled ones)."""
    fps = {}
    for st in pipeline:
        if not st.enabled(cfg):
            fps[st.name] = None
            continue
        upstream = {}
        for store in st.inputs:
            prod = pipeline.producer_of(store, cfg)
            if prod is not None and prod.name != st.name:
                upstream[prod.name] = fps[prod.name].digest
        files = st.files(cfg)
        old = run.manifest(st.name) if run is not None else None
        fps[st.name] = StageFingerprint(config_values(cfg, st.config), upstream,
                                        stage_file_digests(files, old) if files else {})
    return fps


def _queue_state(client, log):
    """The worker jobs' queue state of a SLURM/PBS cluster (:class:`mmflow.workflow.engine.batch.QueueState`),
    None for any other client."""
    poll = getattr(type(client), "queue_state", None)
    return poll(client, log) if poll is not None else None


def _execute(client, ctx, pipeline, name, todo, progress, worker_wait_s, log=print, pool=None, on_done=None):
    """Run the keys ``todo`` of stage ``name``; ``pool``: the stage whose worker pool runs them (default:
    its own; a stage run channel by channel with the one before it runs in that one's); ``on_done(keys)``:
    called on the driver with the keys finished since its last call (what they alone read is released)."""
    if not todo:
        return []
    on_done = on_done or (lambda keys: None)
    bar = Progress(name, len(todo), progress)
    BOARD.begin_batch(name)
    if client is None:
        out = []
        for k in todo:
            out.append(run_task(ctx, pipeline, name, k))
            on_done([k])
            bar.update(len(out))
            BOARD.progress(name, len(out))
        bar.close()
        return out
    from distributed import wait  # deferred: distributed, ~1 s to import; synchronous runs never need it

    use_stage = getattr(type(client), "use_stage", None)
    # SLURM/PBS jobs sized per stage: the stage's own, each task taking its pool's worker cores of a worker's task
    # slots (mmflow.workflow.engine.pools.TASK_SLOT)
    jobs = use_stage(client, pool or name, log) if use_stage is not None else None
    futures = client.map(run_task_reporting_input_errors, [ctx] * len(todo), [pipeline] * len(todo),
                         [name] * len(todo), todo, pure=False, key=[f"{name}-{k}-{ctx.token}" for k in todo],
                         retries=2, resources=None if jobs is None else {TASK_SLOT: jobs["worker_cores"]})
    # the tasks not yet gathered: a gathered task's future is released at once, so that a worker leaving later
    # (retired at its lifetime, a pool's switch, the cluster's close) makes dask recompute nothing of it, which
    # would write its outputs again, maybe after the run has ended (a map's temporary file left behind)
    pending = dict(enumerate(futures))
    del futures
    results = {}
    no_worker_since = said = None
    try:
        while True:
            try:
                wait(list(pending.values()), timeout=1.0)
            except TimeoutError:
                pass
            done = len(results) + sum(f.done() for f in pending.values())
            seen = set(results)
            _gather_stage(client, pending, results)  # every task done by now: its result, or its input error
            on_done([todo[k] for k in results if k not in seen])
            bar.update(done)
            BOARD.progress(name, done)
            if done == len(todo):
                break
            queue = _queue_state(client, log)
            if queue is not None and queue.fatal:
                raise MmflowError(f"stage '{name}': {queue.fatal}")
            waiting = queue.waiting() if queue is not None else None
            if waiting != said:
                if waiting:
                    log(f"[{name}] {waiting}")
                said = waiting
            if client.scheduler_info().get("workers") or (queue is not None and (queue.pending or queue.running)):
                no_worker_since = None  # queued or starting jobs are not dead workers: SLURM/PBS waits may be long
            elif no_worker_since is None:
                no_worker_since = time.time()
            elif time.time() - no_worker_since > worker_wait_s:
                raise MmflowError(
                    f"stage '{name}': no dask worker for {worker_wait_s:g} s with {len(todo) - done} of "
                    f"{len(todo)} tasks unfinished (workers died: memory, walltime, a crash?). Fix: start "
                    "workers (check the cluster's logs), then rerun the same command: finished chunks are kept "
                    "(cluster.worker_wait_s sets the wait)")
    except InputError:  # the stage stops: no task of it may still write when the driver tidies up
        _cancel_and_wait(client, list(pending.values()), f"{name}-", ctx.token)
        raise
    except BaseException:
        client.cancel(list(pending.values()))
        raise
    finally:
        bar.close()
    # every finished task was gathered in the loop: what is left pending ended in error (after its retries)
    client.gather(list(pending.values()))  # raises that error
    return [results[k] for k in range(len(todo))]


#: how long a stage stopped by an input error waits for its tasks already running to end
STOP_WAIT_S = 600.0


def _running(prefix, token, dask_worker=None):
    """The keys of a run's tasks still running on a worker (a cancelled task runs on to its end)."""
    return [ts.key for ts in dask_worker.state.all_running_tasks
            if str(ts.key).startswith(prefix) and str(ts.key).endswith(token)]


def _cancel_and_wait(client, futures, prefix, token, wait_s=STOP_WAIT_S):
    """Cancel a stage's tasks, then wait (up to ``wait_s``) for those already running: dask cannot
    interrupt a running task, and a store must not be removed while a task still writes to it."""
    client.cancel(futures)
    end = time.monotonic() + wait_s
    try:
        while time.monotonic() < end and any(client.run(_running, prefix, token).values()):
            time.sleep(0.2)
    except Exception:  # a worker lost meanwhile (nothing of it runs on): the input error is what to report
        pass


def _gather_stage(client, pending, results):
    """Fetch the results of the tasks finished since the last call (``pending``: ``{index: future}``) into
    ``results`` (``{index: result}``), releasing their futures; raise the first input error a task reported
    (:func:`run_task_reporting_input_errors`)."""
    new = [k for k, f in pending.items() if f.status == "finished"]
    for k, r in zip(new, client.gather([pending[k] for k in new]) if new else []):
        if "input_error" in r:
            raise r["input_error"]
        results[k] = r
        pending.pop(k).release()


def _check_inputs(run, st, cfg, pipeline, after=None):
    """Every input store's producer is complete and its recorded chunks exist with their sizes (but
    ``after``, the stage it runs channel by channel with: its tasks' markers are checked as they are read)."""
    for store in st.inputs:
        prod = pipeline.producer_of(store, cfg)
        if prod is None or prod.name == st.name or prod is after:
            continue
        s = run.stage_status(prod.name)
        if s is None or not s["complete"]:
            raise MmflowError(f"stage '{st.name}' needs stage '{prod.name}' complete in {run.path}: "
                              f"run `mmflow run` (or `mmflow {prod.name}`) first")
        problems = verify_chunks(run.path, run.live_chunk_index(prod.name), full=False)
        if problems:
            raise DamagedStoreError(f"stage '{st.name}' cannot start: the output of stage '{prod.name}' is "
                                    f"damaged: {problems[0]}" + (f" (and {len(problems) - 1} more)"
                                                                  if len(problems) > 1 else "")
                                    + f". Fix: `mmflow run ... --force` recomputes stage '{prod.name}' "
                                    f"(`mmflow verify {run.path}` lists every damaged chunk)")


def _iterate(client, ctx, pipeline, run, st, sctx, progress, worker_wait_s, log):
    """Cycles of an iterative stage, each a map over the keys ``next_cycle`` returns, then a checkpoint.

    ``next_cycle(ctx, cycle)`` runs on the driver, reads the state the previous cycles left in
    the stage's stores, may write this cycle's plan (recorded in the cycle's checkpoint marker)
    and returns the cycle's keys (:class:`TaskKey` values; the runner sets their ``cycle``), or None
    when the loop has converged. A cycle whose checkpoint
    exists is not run again, so a killed loop resumes at the first unfinished cycle; because
    ``next_cycle`` is deterministic, a cycle interrupted half-way is planned identically again.
    """
    results, cycle = [], 0
    while True:
        mark = f"cycle{cycle:04d}"
        if run.is_done(st.name, mark):
            cycle += 1
            continue
        cctx = sctx.for_task()
        keys = st.next_cycle(cctx, cycle)
        release_freed_memory()  # the plan's maps and tables (CLEAN: ~1 GB at lmax 1000) back to the system
        if keys is None:
            log(f"[{st.name}] converged after {cycle} cycles" if st.kind == "iterative"
                else f"[{st.name}] {cycle + 1} phases done")  # a solve or map stage's second phase
            return results
        ckeys = [replace(k, cycle=cycle).format() for k in keys]
        run.add_keys(st.name, ckeys + [mark])
        todo = [k for k in ckeys if not run.is_done(st.name, k)]
        BOARD.add_tasks(st.name, len(ckeys), len(ckeys) - len(todo))
        results += _execute(client, ctx, pipeline, st.name, todo, progress, worker_wait_s, log)
        run.mark_done(st.name, mark, {"cycle": cycle, "tasks": len(keys)}, cctx.ledger.entries)
        cycle += 1


def _kept_summary(run, st, todo):
    """The recorded summary of a stage already complete with the same fingerprint (``begin_stage``
    has refused any other), with ``kept: True`` and ``tasks_run: 0``; None when it has work left,
    including a finalize whose marker :func:`mmflow.workflow.engine.release.repair_or_refuse` removed for a
    damaged file."""
    recorded = None if todo else run.completion(st.name)  # no key left to do: no per-key scan again
    if recorded is None or (st.finalize is not None and not run.is_done(st.name, "_finalize")):
        return None
    return dict(recorded, kept=True, tasks_run=0)


def _counts(run, st):
    """The stage's counters summed over every finished task (this run's and earlier ones)."""
    infos = run.task_infos(st.name).values()
    return {c: sum(int(i.get(c, 0) or 0) for i in infos) for c in st.counters}


def _worker_peak(results):
    """The largest peak resident memory (GB) of a worker process while one of this run's tasks ran
    (None when every task was already done)."""
    peaks = [r["peak_rss_gb"] for r in results if r.get("peak_rss_gb") is not None]
    return max(peaks) if peaks else None


def _has_work(run, name, fp):
    """True when the stage has tasks to do: it is not complete, or complete with other settings."""
    s = run.stage_status(name)
    return s is None or not s["complete"] or s["fingerprint"] != fp.digest


def _stale_stages(run, fps, names):
    return [n for n in names if fps.get(n) is not None and run.is_stale(n, fps[n].digest)]


def run_workflow(cfg, client=None, only=None, force=False, progress=True, log=print, pipeline=PIPELINE,
                 planned=None):
    """Run every enabled stage (or just ``only``) of a workflow; return the per-stage summaries.

    ``pipeline``: the stages in order (:data:`mmflow.workflow.pipeline.PIPELINE`; tests pass their own).
    ``planned``: the names of every stage the whole run will execute, when this call runs only some of
    them (the prior passes run the stages in parts): the stages' checks then judge the inputs for all of
    them before any work, as one call would.
    """
    run = RunDir(cfg.run.directory)
    run.path.mkdir(parents=True, exist_ok=True)
    lock, token = run.acquire_lock()
    logfile = open(run.path / "mmflow.log", "a")

    def log_both(msg):
        logfile.write(f"{time.strftime('%Y-%m-%dT%H:%M:%S')} {msg}\n")
        logfile.flush()
        log(msg)

    try:
        summaries = _run_locked(cfg, run, token, client, only, force, progress, log_both, pipeline, planned)
        BOARD.end_run(run_dir=run.path)
        return summaries
    except BaseException as exc:
        BOARD.end_run(f"{type(exc).__name__}: {exc}", run.path)
        logfile.write(f"{time.strftime('%Y-%m-%dT%H:%M:%S')} stopped: {type(exc).__name__}: {exc}\n")
        if isinstance(exc, InputError):  # no half-made store: a stage none of whose tasks finished is forgotten
            for st in pipeline:
                if run.manifest(st.name) is not None and not run.has_results(st.name):
                    run.reset_stage(st.name)
        run.release_if_unused()  # nothing recorded (refused before any work): the log alone stays
        raise
    finally:
        logfile.close()
        lock.close()


def _open_stage(run, st, cfg, pipeline, fps, ctx, force, log, after=None):
    """A stage up to its tasks: reset if stale (``--force``) or never begun, repaired, its inputs checked
    (``after``: the stage it runs channel by channel with, not complete yet), its keys listed (prepare) and
    recorded. Returns ``(stage context, keys, keys to do, kept summary or None)``."""
    fp = fps[st.name]
    if run.is_stale(st.name, fp.digest) and (force or not run.has_results(st.name)):
        why = "recomputing (--force)" if force else "no task had finished: starting afresh"
        log(f"[{st.name}] {why}: {fp.explain(run.manifest(st.name))}")
        run.reset_stage(st.name)
    repair_or_refuse(run, st, force, log)
    _check_inputs(run, st, cfg, pipeline, after)
    sctx = ctx.for_stage(st)
    pctx = sctx.for_task()
    # a stage whose prepare ran (its marker records what it wrote: kept) and that reads or writes a store
    # released since, whole or in part: its keys as listed then (its prepare would read, or make again, what
    # was released); a stage run channel by channel with another may be half-way
    prepared = run.is_done(st.name, "_prepare") and bool(released_here(run, st, cfg, pipeline))
    keys = planned_keys(run, st.name) if prepared else [k.format() for k in st.prepare(pctx)]
    todo = run.begin_stage(st.name, fp, keys, st.outputs)
    BOARD.begin_stage(st.name, len(keys), len(keys) - len(todo))
    kept = _kept_summary(run, st, todo)
    if kept is None and not prepared:
        run.mark_done(st.name, "_prepare", {}, pctx.ledger.entries)
    if kept is None:
        _stamp_stores(run, st, cfg, fp.digest)
        log(f"[{st.name}] {len(keys)} tasks, {len(keys) - len(todo)} already done: {st.description}")
    return sctx, keys, todo, kept


def _close_stage(run, st, cfg, sctx, t0, results, client, ctx, pipeline, progress, worker_wait_s, log):
    """A stage after its tasks: its further phases or cycles, its finalize, its summary; marked complete."""
    if st.next_cycle is not None:  # iterative stages, and solve stages with a second phase
        results += _iterate(client, ctx, pipeline, run, st, sctx, progress, worker_wait_s, log)
    fin = None
    if st.finalize:
        fctx = sctx.for_task()
        fin = st.finalize(fctx)
        run.mark_done(st.name, "_finalize", fin, fctx.ledger.entries)
        if isinstance(fin, dict) and fin.get("log"):  # what the stage chose that a user should read
            log(f"[{st.name}] {fin['log']}")
    counts = _counts(run, st)
    if any(counts.values()):
        log(f"[{st.name}] " + ", ".join(f"{k.replace('_', ' ')}: {v}" for k, v in counts.items() if v))
    # every phase's tasks (a second phase's or a cycle's keys join the manifest as they are planned)
    n_tasks = sum(1 for k in run.manifest(st.name)["keys"] if not k.startswith("cycle"))
    summary = {"stage": st.name, "wall_s": round(time.time() - t0, 2), "tasks": n_tasks, "counts": counts,
               "tasks_run": sum(1 for r in results if not r.get("skipped")),
               "task_s": round(sum(r.get("seconds", 0) for r in results), 3),
               "checksum_s": round(sum(r.get("checksum_s", 0) for r in results), 3),
               "guard_s": round(sum(r.get("guard_s", 0) for r in results), 3),
               "bytes_written": run.bytes_of(st.outputs), "finalize": fin,
               "worker_peak_rss_gb": _worker_peak(results),
               "driver_peak_rss_gb": gb(peak_rss_bytes())}
    run.finish_stage(st.name, summary)
    BOARD.finish_stage(st.name, summary["wall_s"])
    log(f"[{st.name}] done in {summary['wall_s']} s, {summary['tasks_run']} tasks run, "
        f"{summary['bytes_written'] / 1e6:.1f} MB in {', '.join(st.outputs)}")
    return summary


def _run_locked(cfg, run, token, client, only, force, progress, log, pipeline, planned=None):
    stages = [st for st in pipeline if not only or st.name in only]
    fps = stage_fingerprints(cfg, run, pipeline)
    stale = [n for n in _stale_stages(run, fps, [st.name for st in stages if st.task is not None])
             if run.has_results(n)]  # a stage that never finished a task starts afresh
    if stale and not force:  # refuse before any work, naming what changed
        st = stale[0]
        raise _stale_error(run, st, fps[st], stale)
    running = list(planned) if planned else [st.name for st in stages if st.enabled(cfg)]
    for st in stages:  # refuse inputs the run cannot use before any work
        if st.check is not None and st.enabled(cfg):
            st.check(cfg, running)
    for st in stages:  # then the checks that read the input data, for the stages with tasks to do
        if st.scan is not None and st.enabled(cfg) and _has_work(run, st.name, fps[st.name]):
            st.scan(cfg)
    recompute_released(run, cfg, pipeline, fps, stages, force, log, later=planned or ())
    plan = _check_resources(cfg, run, client, stages)
    slots = 1 if client is None else cfg.cluster.n_workers * cfg.cluster.threads_per_worker  # as mmflow plan counts
    BOARD.begin_run(run.path, cluster_kind(client), [st.name for st in stages if st.enabled(cfg) and st.task],
                    plan, slots)
    (run.path / "config.yaml").write_text(yaml.safe_dump(json.loads(cfg.model_dump_json()), sort_keys=False))
    (run.path / "run.json").write_text(json.dumps({"name": cfg.run.name, "versions": versions(),
                                                   "cluster": cluster_record(cfg, client)}, indent=2))
    ctx = Context(cfg.model_dump_json(), str(run.path), token)
    worker_wait_s = float(getattr(cfg.cluster, "worker_wait_s", 300))
    summaries, paired = {}, set()
    for st in stages:
        if not st.enabled(cfg):
            if st.task is None or only:
                log(f"[{st.name}] skipped: disabled ({st.description})")
            continue
        if st.name in paired:  # run channel by channel with the stage before it
            continue
        t0 = time.time()
        reset_peak_rss()
        sctx, keys, todo, kept = _open_stage(run, st, cfg, pipeline, fps, ctx, force, log)
        if kept is not None:  # finished with these settings and inputs: nothing is recomputed or rewritten
            summaries[st.name] = kept
            BOARD.keep_stage(st.name, len(keys))
            log(f"[{st.name}] complete, kept: {len(keys)} tasks done (took {kept.get('wall_s')} s when it ran)")
            release_finished(run, cfg, pipeline, fps, log)
            continue
        nxt = by_channel_partner(st, stages, cfg)
        if nxt is not None:
            nctx, nkeys, ntodo, nkept = _open_stage(run, nxt, cfg, pipeline, fps, ctx, force, log, after=st)
            if nkept is None:  # both have work: channel by channel, each channel's intermediates released
                paired.add(nxt.name)
                runs, spent = by_channel(run, cfg, pipeline, st, nxt, todo, ntodo, nkeys, log,
                                         lambda name, keys: _execute(client, ctx, pipeline, name, keys, progress,
                                                                     worker_wait_s, log, pool=st.name))
                for s_, c_ in ((st, sctx), (nxt, nctx)):  # each stage's wall time: its own batches and close
                    summaries[s_.name] = _close_stage(run, s_, cfg, c_, time.time() - spent[s_.name], runs[s_.name],
                                                      client, ctx, pipeline, progress, worker_wait_s, log)
                release_finished(run, cfg, pipeline, fps, log)
                continue
        on_done = None
        if chunk_releases(st, cfg, pipeline):  # the chunks its finished tasks alone read go as they finish
            def on_done(done, st=st):
                release_task_chunks(run, cfg, pipeline, fps, st, done, log)
            on_done([k for k in keys if k not in set(todo)])  # a resumed stage's, and a killed release's
        results = _execute(client, ctx, pipeline, st.name, todo, progress, worker_wait_s, log, on_done=on_done)
        summaries[st.name] = _close_stage(run, st, cfg, sctx, t0, results, client, ctx, pipeline, progress,
                                          worker_wait_s, log)
        release_finished(run, cfg, pipeline, fps, log)
    if only:
        later = _stale_stages(run, stage_fingerprints(cfg, run, pipeline), list(pipeline.names))
        if later:
            log(f"stages now made from older inputs (STALE): {', '.join(later)}. Refresh them with "
                f"`mmflow run WORKFLOW ... --force` (the same settings; up-to-date stages are kept)")
    summary_path = run.path / "summary.json"
    fresh = {k: v for k, v in summaries.items() if not v.get("kept")}  # kept stages keep their record
    if fresh:
        merged = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        merged.update(fresh)
        summary_path.write_text(json.dumps(merged, indent=2))
    return summaries


def _worker_limit_gb(client):
    """The memory (GB) a task has on the cluster's workers: the smallest of their memory limits, each over
    the tasks the worker runs at once (its threads; where it has :data:`TASK_SLOT`, jobs sized per stage,
    its whole limit: the plan sized them, and each task takes its share); the machine's memory in process
    (no client); None when no worker has joined yet or none has a limit. A worker of four threads runs
    four tasks at once in its one limit."""
    if client is None:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9
    shares = [(w.get("memory_limit") or 0) / (1 if TASK_SLOT in (w.get("resources") or {}) else w.get("nthreads") or 1)
              for w in client.scheduler_info().get("workers", {}).values()]
    shares = [x for x in shares if x > 0]
    return min(shares) / 1e9 if shares else None


def _check_resources(cfg, run, client, stages):
    """Before any work: the largest task of each stage still to run against a worker's memory, and
    the stores against the free disk (:func:`mmflow.workflow.plan.planner.check_fits`); returns the plan of those
    stages (:class:`mmflow.workflow.plan.planner.StageEstimate`, one task slot each), for the dashboard."""
    todo = [st for st in stages if st.enabled(cfg) and st.task is not None
            and not (run.stage_status(st.name) or {}).get("complete")]
    if not todo:
        return []
    return check_fits(cfg, _worker_limit_gb(client), [st.name for st in todo],
                      existing_bytes=run.bytes_of([o for st in todo for o in st.outputs]))


def _stale_error(run, stage, fp, stale):
    others = [s for s in stale if s != stage]
    return StaleOutputError(
        f"stage '{stage}' in {run.path} was made from other settings or inputs: {fp.explain(run.manifest(stage))}"
        + (f" (stale too: {', '.join(others)})" if others else "")
        + ". Fix: add --force to recompute it and the stages after it (up-to-date stages are kept), "
        "or use a new directory with run.directory=...")


def _stamp_stores(run, stage, cfg, fingerprint):
    """Record the resolved configuration, versions and fingerprint in every zarr store a stage writes."""
    for out in stage.outputs:
        path = run.store(out)
        if out.endswith(".zarr") and path.exists():
            zarr.open_group(str(path), mode="r+").attrs.update(
                {"mmflow": {"stage": stage.name, "fingerprint": fingerprint, "versions": versions(),
                            "config": json.loads(cfg.model_dump_json())}})


def status(run_path):
    """Per stage: chunks done, complete, and stale (made from other settings than ``config.yaml``)."""
    run = RunDir(run_path)
    if not run.path.is_dir():
        raise InputError(str(run.path), "run directory", "does not exist",
                         "give the run.directory of a workflow that has run")
    try:
        fps = stage_fingerprints(load_config(run.path / "config.yaml"), run)
    except InputError:  # no config.yaml, or one from another mmflow version: staleness unknown
        fps = None
    out = {}
    for st in PIPELINE:
        s = run.stage_status(st.name)
        if s is not None:  # stale: results made from other settings (a stage without any starts afresh)
            s["stale"] = None if fps is None else (bool(fps.get(st.name)) and s["fingerprint"] != fps[st.name].digest
                                                   and run.has_results(st.name))
        out[st.name] = s
    return out


def verify(run_path, full=True):
    """``{stage: [problems]}``: missing markers, missing, truncated or changed chunk files."""
    run = RunDir(run_path)
    if not run.path.is_dir():
        raise InputError(str(run.path), "run directory", "does not exist", "give an existing run directory")
    return run.verify(list(PIPELINE.names), full)
