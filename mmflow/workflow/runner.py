"""Run stages in order on a dask client, resumably, with a progress bar and a summary per stage."""
from __future__ import annotations

import json
import os
import time
from importlib.metadata import PackageNotFoundError, version

import yaml

from mmflow.errors import MmflowError
from mmflow.workflow.config import config_fingerprint
from mmflow.workflow.context import Context
from mmflow.workflow.stages.base import all_stages, get_stage

PACKAGES = ("mmflow", "numpy", "scipy", "dask", "distributed", "zarr", "healpy", "astropy", "ducc0", "pyuvdata")


def versions():
    out = {}
    for p in PACKAGES:
        try:
            out[p] = version(p)
        except PackageNotFoundError:
            out[p] = None
    return out


def run_task(ctx, stage_name, key):
    """Worker side: skip if marked done, else compute, write, then mark (atomically)."""
    run = ctx.run
    if run.is_done(stage_name, key):
        return {"key": key, "skipped": True}
    delay = float(os.environ.get("MMFLOW_TASK_DELAY_S", "0") or 0)
    if delay:  # a knob to slow tasks down: watch the dashboard, or test kills mid-stage
        time.sleep(delay)
    t0 = time.time()
    info = get_stage(stage_name).task(ctx, key) or {}
    info = dict(info, seconds=round(time.time() - t0, 3))
    run.mark_done(stage_name, key, info)
    return {"key": key, "skipped": False, **info}


def stage_fingerprints(cfg):
    """Fingerprint of every stage: its config sections plus its enabled upstream stages."""
    fps = {}
    for st in all_stages():
        if not st.enabled(cfg):
            fps[st.name] = None
            continue
        up = [fps.get(u) for u in st.upstream if fps.get(u)]
        fps[st.name] = config_fingerprint(cfg, st.sections) + ("" if not up else "-" + config_fingerprint_of(up))
    return fps


def config_fingerprint_of(items):
    import hashlib

    return hashlib.sha256("|".join(items).encode()).hexdigest()[:16]


def _execute(client, ctx, name, todo, progress):
    if not todo:
        return []
    if client is None:
        return [run_task(ctx, name, k) for k in todo]
    futures = client.map(run_task, [ctx] * len(todo), [name] * len(todo), todo, pure=False,
                         key=[f"{name}-{k}-{ctx.run_path}" for k in todo], retries=2)
    if progress:
        from distributed import progress as dprogress

        dprogress(futures)
        print()
    return client.gather(futures)


def run_workflow(cfg, client=None, only=None, force=False, progress=True, log=print):
    """Run every enabled stage (or just ``only``) of a workflow; return the per-stage summaries."""
    ctx = Context(cfg.model_dump_json(), cfg.run.directory)
    run = ctx.run
    run.path.mkdir(parents=True, exist_ok=True)
    (run.path / "config.yaml").write_text(yaml.safe_dump(json.loads(cfg.model_dump_json()), sort_keys=False))
    (run.path / "run.json").write_text(json.dumps({"name": cfg.run.name, "versions": versions()}, indent=2))
    fps = stage_fingerprints(cfg)
    summaries = {}
    for st in all_stages():
        if only and st.name not in only:
            continue
        if not st.enabled(cfg):
            if st.task is None or only:
                log(f"[{st.name}] skipped: disabled ({st.description})")
            continue
        for up in st.upstream:
            ups = run.stage_status(up)
            if fps.get(up) and (ups is None or not ups["complete"]):
                raise MmflowError(f"stage '{st.name}' needs stage '{up}' complete in {run.path}: "
                                  f"run `mmflow run` (or `mmflow {up}`) first")
        t0 = time.time()
        if force and run.is_stale(st.name, fps[st.name]):
            run.reset_stage(st.name, st.outputs)
        keys = st.prepare(ctx)
        todo = run.begin_stage(st.name, fps[st.name], keys, st.outputs)
        _stamp_stores(run, st, cfg, fps[st.name])
        log(f"[{st.name}] {len(keys)} tasks, {len(keys) - len(todo)} already done: {st.description}")
        results = _execute(client, ctx, st.name, todo, progress)
        fin = st.finalize(ctx) if st.finalize else None
        summary = {"stage": st.name, "wall_s": round(time.time() - t0, 2), "tasks": len(keys),
                   "tasks_run": sum(1 for r in results if not r.get("skipped")),
                   "bytes_written": run.bytes_of(st.outputs), "finalize": fin}
        run.finish_stage(st.name, summary)
        summaries[st.name] = summary
        log(f"[{st.name}] done in {summary['wall_s']} s, {summary['tasks_run']} tasks run, "
            f"{summary['bytes_written'] / 1e6:.1f} MB in {', '.join(st.outputs)}")
    summary_path = run.path / "summary.json"
    merged = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    merged.update(summaries)
    summary_path.write_text(json.dumps(merged, indent=2))
    return summaries


def _stamp_stores(run, stage, cfg, fingerprint):
    """Record the resolved configuration, versions and fingerprint in every zarr store a stage writes."""
    import zarr

    for out in stage.outputs:
        path = run.store(out)
        if out.endswith(".zarr") and path.exists():
            zarr.open_group(str(path), mode="r+").attrs.update(
                {"mmflow": {"stage": stage.name, "fingerprint": fingerprint, "versions": versions(),
                            "config": json.loads(cfg.model_dump_json())}})


def status(run_path):
    """Per stage: chunks done, complete, and stale (made from other settings than ``config.yaml``)."""
    from mmflow.errors import InputError
    from mmflow.workflow.config import load_config
    from mmflow.workflow.rundir import RunDir

    run = RunDir(run_path)
    try:
        fps = stage_fingerprints(load_config(run.path / "config.yaml"))
    except InputError:  # no config.yaml, or one from another mmflow version: staleness unknown
        fps = None
    out = {}
    for st in all_stages():
        s = run.stage_status(st.name)
        if s is not None:
            s["stale"] = None if fps is None else bool(fps.get(st.name)) and s["fingerprint"] != fps[st.name]
        out[st.name] = s
    return out
