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
from mmflow.io.run_stores import RELEASED_BY_CHUNK, array_paths
from mmflow.workflow.engine.task_key import TaskKey


def finished(run, name, fps):
    """True when stage ``name`` is complete with its current fingerprint."""
    return finished_keys(run, name, fps) and run.completion(name) is not None


def released_here(run, st, cfg, pipeline):
    """The stores among ``st``'s inputs and outputs that the run has released, whole or some of their arrays."""
    out = []
    for store in (*st.inputs, *st.outputs):
        writer = pipeline.producer_of(store, cfg)
        if writer is not None and any(u.split("/", 1)[0] == store for u in run.released(writer.name)):
            out.append(store)
    return out


def released_reads(run, st, cfg, pipeline, fps=None):
    """``[(writer, unit)]``: what ``st`` reads that the run has released: a store (``partials.zarr``) or an
    array of one it reads (``vis.zarr/vis``: :meth:`Pipeline.array_readers`). An array released in part by
    ``st``'s own tasks (:func:`release_task_chunks`) is not, while those tasks stay finished with the current
    fingerprint ``fps`` (:func:`_read_again`): only they read those chunks."""
    out = []
    for store in st.inputs:
        prod = pipeline.producer_of(store, cfg)
        if prod is None or prod.name == st.name:
            continue
        for unit, rec in run.released(prod.name).items():
            name, _, array = unit.partition("/")
            if name == store and (not array or store not in st.reads or array in st.reads[store]) and (
                    _read_again(run, st, rec, fps)):
                out.append((prod, unit))
    return out


def _read_again(run, st, rec, fps):
    """False where what a release record holds is chunks that only finished tasks of ``st`` read (its ``by``),
    which stay finished with ``st``'s current fingerprint and intact: ``st`` will not read them again."""
    by = rec.get("by")
    if not by or set(by) != {st.name} or fps is None or not finished_keys(run, st.name, fps):
        return True
    damaged = run.damaged_keys(st.name)
    return not all(run.is_done(st.name, k) and k not in damaged for k in by[st.name])


def finished_keys(run, name, fps):
    """True where stage ``name`` has begun with its current fingerprint (its finished keys stand)."""
    man = run.manifest(name)
    return man is not None and fps.get(name) is not None and man["fingerprint"] == fps[name].digest


def chunk_releases(st, cfg, pipeline):
    """``[(writer, unit, axis, key field)]``: the arrays released after ``st`` (:meth:`Pipeline.released_arrays`)
    whose chunks go task by task (:data:`mmflow.io.run_stores.RELEASED_BY_CHUNK`, ``Stage.task_chunks``)."""
    out = []
    for unit, after in pipeline.released_arrays(cfg).items():
        store, _, array = unit.partition("/")
        dim, axis, arrays = RELEASED_BY_CHUNK.get(store, (None, None, ()))
        if after == st.name and array in arrays and dim in st.task_chunks:
            out.append((pipeline.producer_of(store, cfg), unit, axis, st.task_chunks[dim]))
    return out


def release_task_chunks(run, cfg, pipeline, fps, st, keys, log):
    """Release the chunks that the finished tasks ``keys`` of ``st`` read alone (:func:`chunk_releases`: a
    baseline chunk of vis.zarr's visibilities and weights once the mmodes task of that chunk has finished),
    where the writer and every other stage that reads the array are complete. Recorded with the writer
    (:meth:`RunDir.release_arrays`, ``by`` the tasks), so a resume that would run one of those tasks again
    (other settings, a damaged chunk) recomputes the writer first (:func:`recompute_released`)."""
    for writer, unit, axis, field in chunk_releases(st, cfg, pipeline):
        store, _, array = unit.partition("/")
        others = [s for s in pipeline.array_readers(store, array, cfg) if s.name != st.name]
        done = [k for k in keys if run.is_done(st.name, k)]
        if not done or not all(finished(run, s.name, fps) for s in [writer, *others]):
            continue
        root = run.store(store)
        paths = [str(d.relative_to(root)) for k in done
                 for d in sorted(root.glob("/".join([array, "c", *["*"] * axis, str(getattr(TaskKey.parse(k),
                                                                                          field))])))
                 if d.is_dir()]
        if not paths:
            continue
        before = run.released(writer.name).get(unit, {}).get("bytes", 0)
        nbytes = run.release_arrays(writer.name, unit, paths, by={st.name: done})
        if nbytes is not None and nbytes > before:
            log(f"[{writer.name}] freed {len(paths)} chunk folders of {unit} ({(nbytes - before) / 1e6:.1f} MB): "
                f"read by {st.name}'s finished tasks {', '.join(done)} alone (run.keep keeps them)")


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
        again = record is not None and "by" not in record  # not: released in part, task by task
        _logged(log, writer, unit, readers, run.release_arrays(writer.name, unit, paths), again)


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
        for prod, store in released_reads(run, st, cfg, pipeline, fps):
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
