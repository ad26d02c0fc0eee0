"""Stores with a lifetime: a run's intermediates released once the stages that read them have finished.

Which stores are released, and after which stage, derives from the stages' declared inputs
(:meth:`mmflow.workflow.pipeline.Pipeline.released`: :data:`mmflow.io.run_stores.RELEASED_BY_DEFAULT`
less ``run.keep``); the large arrays of kept stores likewise, from the arrays each stage reads
(:meth:`mmflow.workflow.pipeline.Pipeline.released_arrays`: :data:`mmflow.io.run_stores.RELEASED_ARRAYS`,
``Stage.reads``), recorded as ``store/array`` (``vis.zarr/vis``). The runner calls :func:`release_finished`
after every stage (run or kept) and :func:`recompute_released` before any work: a released store is recorded
with its writer
(:meth:`mmflow.workflow.engine.rundir.RunDir.release`), so a resume knows it was finished; a stage
that must run again and reads one has the store's writer recomputed first (stages are deterministic:
the same bits), and a resume whose remaining stages do not read it recomputes nothing.
:func:`repair_or_refuse` recomputes a stage's damaged chunks (``--force``), with the tasks that wrote a
store of its own it has released since.
"""
from __future__ import annotations

from mmflow.errors import MmflowError
from mmflow.io.stores import DamagedStoreError
from mmflow.io.run_stores import array_paths
from mmflow.workflow.engine.task_key import TaskKey


def finished(run, name, fps):
    """True when stage ``name`` is complete with its current fingerprint."""
    man = run.manifest(name)
    return (man is not None and fps.get(name) is not None and man["fingerprint"] == fps[name].digest
            and run.completion(name) is not None)


def released_here(run, st, cfg, pipeline):
    """The stores among ``st``'s inputs and outputs that the run has released, whole or some of their arrays."""
    out = []
    for store in (*st.inputs, *st.outputs):
        writer = pipeline.producer_of(store, cfg)
        if writer is not None and any(u.split("/", 1)[0] == store for u in run.released(writer.name)):
            out.append(store)
    return out


def released_reads(run, st, cfg, pipeline):
    """``[(writer, unit)]``: what ``st`` reads that the run has released: a store (``partials.zarr``) or an
    array of one it reads (``vis.zarr/vis``: :meth:`Pipeline.array_readers`)."""
    out = []
    for store in st.inputs:
        prod = pipeline.producer_of(store, cfg)
        if prod is None or prod.name == st.name:
            continue
        for unit in run.released(prod.name):
            name, _, array = unit.partition("/")
            if name == store and (not array or store not in st.reads or array in st.reads[store]):
                out.append((prod, unit))
    return out


def planned_keys(run, name):
    """The keys a stage's prepare listed when it ran (its manifest's, less those a later phase added): what
    a finished stage that reads or writes a released store is kept with, its prepare not run again (it would
    open the released store, or make it again empty)."""
    man = run.manifest(name)
    return [k for k in man["keys"] if k not in set(man.get("added_keys", []))]


def release_finished(run, cfg, pipeline, fps, log):
    """Release every intermediate of :meth:`Pipeline.released` whose writer and enabled readers are all
    complete with the current settings (:meth:`RunDir.release`: only the run's own store; a link to
    another run's, in a prior pass, stays)."""
    for store in pipeline.released(cfg):
        writer = pipeline.producer_of(store, cfg)
        readers = pipeline.readers(store, cfg)
        if not all(finished(run, st.name, fps) for st in [writer, *readers]):
            continue
        again = store in run.released(writer.name)  # released; or a kill came between the record and the removal
        if again and not (run.store(store).is_dir() and not run.store(store).is_symlink()):
            continue
        _logged(log, writer, store, readers, run.release(writer.name, store), again)
    for unit in pipeline.released_arrays(cfg):
        store, _, array = unit.partition("/")
        writer = pipeline.producer_of(store, cfg)
        readers = pipeline.array_readers(store, array, cfg)
        if not all(finished(run, st.name, fps) for st in [writer, *readers]):
            continue
        record = run.released(writer.name).get(unit)
        paths = array_paths(run.store(store), store, array)
        if not paths:  # never written (the cross hands of a run without them), or released and removed
            continue
        _logged(log, writer, unit, readers, run.release_arrays(writer.name, unit, paths), record is not None)


def _logged(log, writer, what, readers, nbytes, again):
    """Log a release (not the removal of what a killed release left)."""
    if nbytes is not None and not again:
        by = ", ".join(st.name for st in readers) or f"{writer.name} itself"
        size = f"{nbytes / 1e9:.2f} GB" if nbytes >= 1e8 else f"{nbytes / 1e6:.1f} MB"
        log(f"[{writer.name}] released {what} ({size}): read by {by}, all finished (run.keep keeps it)")


def recompute_released(run, cfg, pipeline, fps, stages, force, log, later=()):
    """The writers of released stores (or arrays) that a stage with work to do reads, reset so that they run again
    (first, bit for bit: stages are deterministic); raise where such a writer is not among ``stages``.

    A stage has work when it is not complete with its current settings (stale with ``--force``, or
    forgotten), or has damaged chunks to recompute (``--force``); a writer reset has work in turn.
    ``later``: the names of every stage the whole run executes, where this call runs only some (a run in
    phases: :func:`mmflow.workflow.engine.passes.run_with_passes`): a writer among ``stages`` that a later
    phase's stage needs is recomputed now (the later phase could not)."""
    names = {st.name for st in stages}
    cands = list(stages) + [pipeline.stage(n) for n in later if n not in names]
    work = {st.name for st in cands if st.enabled(cfg) and st.task is not None
            and (not finished(run, st.name, fps) or (force and run.damaged_keys(st.name)))}
    again, todo = [], list(work)
    while todo:
        st = pipeline.stage(todo.pop())
        for prod, store in released_reads(run, st, cfg, pipeline):
            if prod.name in work:
                continue
            if prod.name not in names | set(later):
                raise MmflowError(f"stage '{st.name}' reads {store}, which stage '{prod.name}' wrote and this run "
                                  f"released in {run.path} once its readers had finished. Fix: run `mmflow run` "
                                  f"(it recomputes stage '{prod.name}' first), or keep it: "
                                  f"run.keep=[{store.split('/')[0]}]")
            work.add(prod.name)
            todo.append(prod.name)
            again.append((prod.name, store, st.name))
    for prod in dict.fromkeys(p for p, _, _ in again):
        what = "; ".join(f"{reader} reads {store}" for p, store, reader in again if p == prod)
        log(f"[{prod}] recomputing: {what}, released after its readers had finished")
        run.reset_stage(prod)


def repair_or_refuse(run, st, force, log):
    """A finished chunk whose files are missing or truncated: recompute it (``--force``) or stop.

    Only the damaged tasks are recomputed, in a stage with cycles too: a later task read the damaged
    chunk while it was intact (every read is checked against the chunk records), so what it wrote
    stands, and a task rerun from the same inputs rewrites its chunk bit for bit. The checkpoint of
    each cycle that holds a damaged task is forgotten with it, so that the cycle is planned again
    (``next_cycle`` is deterministic) and runs just that task.
    """
    stage = st.name
    damaged = run.damaged_keys(stage)
    if not damaged:
        return
    first = next(iter(damaged.values()))[0]
    n = sum(len(p) for p in damaged.values())
    if not force:
        raise DamagedStoreError(f"stage '{stage}' in {run.path} has {n} damaged chunk files (first: {first}). "
                                f"Fix: rerun the same command with --force to recompute the {len(damaged)} damaged "
                                f"tasks (the rest is kept); `mmflow verify {run.path}` lists them all")
    # a store of the stage's own released meanwhile (the diffuse sky's samples, which its time chunks read):
    # the tasks that wrote it run again too, and it is released again once the stage is complete
    again = run.keys_writing_released(stage)
    log(f"[{stage}] recomputing {len(damaged)} tasks whose files are damaged (first: {first})"
        + (f" and the {len(again)} that wrote {', '.join(run.released(stage))}, released since" if again else ""))
    keys = list(damaged) + [k for k in again if k not in damaged]
    arrays = again and any("/" in u for u in run.released(stage))  # gone from a kept store: made by prepare
    run.forget_released(stage)
    if "_prepare" in keys or arrays:
        run.reset_stage(stage)
        return
    cycles = {TaskKey.parse(k).cycle for k in keys if not k.startswith("cycle") and not k.startswith("_")}
    run.forget_keys(stage, keys + [f"cycle{c:04d}" for c in cycles if c is not None])
