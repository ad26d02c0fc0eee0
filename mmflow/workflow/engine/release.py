"""Stores with a lifetime: a run's intermediates released once the stages that read them have finished.

Which stores are released, and after which stage, derives from the stages' declared inputs
(:meth:`mmflow.workflow.pipeline.Pipeline.released`: :data:`mmflow.io.run_stores.RELEASED_BY_DEFAULT`
less ``run.keep``). The runner calls :func:`release_finished` after every stage (run or kept) and
:func:`recompute_released` before any work: a released store is recorded with its writer
(:meth:`mmflow.workflow.engine.rundir.RunDir.release`), so a resume knows it was finished; a stage
that must run again and reads one has the store's writer recomputed first (stages are deterministic:
the same bits), and a resume whose remaining stages do not read it recomputes nothing.
"""
from __future__ import annotations

from mmflow.errors import MmflowError


def finished(run, name, fps):
    """True when stage ``name`` is complete with its current fingerprint."""
    man = run.manifest(name)
    return (man is not None and fps.get(name) is not None and man["fingerprint"] == fps[name].digest
            and run.completion(name) is not None)


def released_here(run, st, cfg, pipeline):
    """The stores among ``st``'s inputs and outputs that the run has released."""
    out = []
    for store in (*st.inputs, *st.outputs):
        writer = pipeline.producer_of(store, cfg)
        if writer is not None and store in run.released(writer.name):
            out.append(store)
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
        nbytes = run.release(writer.name, store)
        if nbytes is not None and not again:
            by = ", ".join(st.name for st in readers) or f"{writer.name} itself"
            size = f"{nbytes / 1e9:.2f} GB" if nbytes >= 1e8 else f"{nbytes / 1e6:.1f} MB"
            log(f"[{writer.name}] released {store} ({size}): read by {by}, all finished "
                "(run.keep keeps it)")


def recompute_released(run, cfg, pipeline, fps, stages, force, log):
    """The writers of released stores that a stage with work to do reads, reset so that they run again
    (first, bit for bit: stages are deterministic); raise where such a writer is not among ``stages``.

    A stage has work when it is not complete with its current settings (stale with ``--force``, or
    forgotten), or has damaged chunks to recompute (``--force``); a writer reset has work in turn."""
    names = {st.name for st in stages}
    work = {st.name for st in stages if st.enabled(cfg) and st.task is not None
            and (not finished(run, st.name, fps) or (force and run.damaged_keys(st.name)))}
    again, todo = [], list(work)
    while todo:
        st = pipeline.stage(todo.pop())
        for store in st.inputs:
            prod = pipeline.producer_of(store, cfg)
            if prod is None or prod.name in work or store not in run.released(prod.name):
                continue
            if prod.name not in names:
                raise MmflowError(f"stage '{st.name}' reads {store}, which stage '{prod.name}' wrote and this run "
                                  f"released in {run.path} once its readers had finished. Fix: run `mmflow run` "
                                  f"(it recomputes stage '{prod.name}' first), or keep it: run.keep=[{store}]")
            work.add(prod.name)
            todo.append(prod.name)
            again.append((prod.name, store, st.name))
    for prod, store, reader in again:
        log(f"[{prod}] recomputing: {reader} reads {store}, released after its readers had finished")
        run.reset_stage(prod)
