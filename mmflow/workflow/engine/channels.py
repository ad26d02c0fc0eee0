"""Two stages run channel by channel: the second's tasks of each channel right after the first's.

A stage that sums what the stage before it wrote per channel (``normal`` after ``transfer``:
``Stage.by_channel_after``) need not wait for every channel of it: the runner alternates them,
channel ``F`` of the first, then channel ``F`` of the second, and releases the first's group ``f{F}`` of
each store the second is the last reader of (:meth:`mmflow.workflow.pipeline.Pipeline.released`: the
partials) once the second's tasks of ``F`` are done. What is on disk at once is then one channel's
partial normal equations, not every channel's (``docs/planning.md``); the tasks, and so every bit they
write, are those of the two stages run one after the other. Within a channel the tasks run in parallel as
before, all in the first stage's worker pool (:mod:`mmflow.workflow.engine.pools`: switching pools at every
channel would wait for new jobs each time). The release is recorded with the first stage as
``store/f{F}`` (:meth:`mmflow.workflow.engine.rundir.RunDir.release_arrays`), so a resume, a stale second
stage or ``--force`` find it as any release (:mod:`mmflow.workflow.engine.release`).
"""
from __future__ import annotations

import time

from mmflow.workflow.engine.task_key import TaskKey


def by_channel_partner(st, stages, cfg):
    """The enabled stage among ``stages`` that runs channel by channel after ``st`` (None if none)."""
    return next((s for s in stages if s.by_channel_after == st.name and s.enabled(cfg)), None)


def channel_of(key):
    """The channel of a task key (its ``freq``; -1 for a key without one, run with the first channel)."""
    f = TaskKey.parse(key).freq
    return -1 if f is None else f


def by_channel(run, cfg, pipeline, first, second, todo, second_todo, second_keys, log, execute):
    """Run ``first``'s keys ``todo`` and ``second``'s ``second_todo`` channel by channel (``execute(stage name,
    keys) -> results``), releasing after each channel what :func:`release_channel` may; returns
    ``{stage name: results}`` and ``{stage name: seconds its batches took}`` (each stage's own wall time)."""
    out, spent = {first.name: [], second.name: []}, {first.name: 0.0, second.name: 0.0}
    for f in sorted({channel_of(k) for k in [*todo, *second_keys]}):
        for st, keys in ((first, todo), (second, second_todo)):
            t0 = time.time()
            out[st.name] += execute(st.name, [k for k in keys if channel_of(k) == f])
            spent[st.name] += time.time() - t0
        release_channel(run, cfg, pipeline, first, second, second_keys, f, log)
    return out, spent


def release_channel(run, cfg, pipeline, first, second, second_keys, f, log):
    """Release channel ``f``'s group ``f{f}`` of each store ``first`` writes and ``second`` is the last reader
    of (:meth:`Pipeline.released`; not with ``run.keep``), once every key of ``second`` for ``f`` is done."""
    if f < 0 or not all(run.is_done(second.name, k) for k in second_keys if channel_of(k) == f):
        return
    released = pipeline.released(cfg)
    for store in first.outputs:
        if released.get(store) != second.name or not (run.store(store) / f"f{f}").is_dir():
            continue
        nbytes = run.release_arrays(first.name, f"{store}/f{f}", [f"f{f}"])
        if nbytes is not None:
            log(f"[{first.name}] released {store}/f{f} ({nbytes / 1e6:.1f} MB): channel {f}, summed by "
                f"{second.name} (run.keep keeps it)")
