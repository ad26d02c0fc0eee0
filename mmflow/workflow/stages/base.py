"""The stage record: what one step of the pipeline reads, writes and runs.

The stages in order live in :mod:`mmflow.workflow.pipeline` (the one list; the runner, the CLI
and the corrections on read derive from it). Each stage module defines one ``STAGE``.

A stage declares what it reads and writes; the runner derives everything else from that:

* ``config``: dotted configuration paths it reads (enforced by
  :class:`mmflow.workflow.engine.fingerprint.ConfigView`); ``inputs``: stores it reads;
  ``files``: a function giving the user files it reads. Together with its inputs'
  fingerprints these make its fingerprint.
* ``outputs``: stores (``*.zarr``, removed whole by ``--force``) or folders whose files the
  tasks list in their markers (only those are ever removed).
* ``prepare(ctx) -> keys`` runs once on the driver (create-or-validate its stores, list its
  work keys, :class:`~mmflow.workflow.engine.task_key.TaskKey` values; the keys may depend on the data and
  the configuration, never on the cluster); ``task(ctx, key)`` runs per key on the workers (``key``
  a ``TaskKey``; its completion marker is named by ``key.format()``); ``finalize(ctx)`` runs on the
  driver at the end (its dict goes into the stage's summary; its ``log`` entry, where it has one, is printed).
* ``check(cfg, stage_names)``, optional, runs on the driver before the run does any work (before
  any stage's prepare), knowing which stages the run will execute: it refuses inputs the run
  cannot use (an ingested observation too short to make m-modes) instead of failing stages later.
* ``scan(cfg)``, optional, a check that reads the input data (non-finite samples): run after the
  checks, before any work and before the cluster starts, but only when the stage has tasks to do.

Kinds (``kind``): ``map`` (independent tasks over keys: time chunks, baseline groups,
m blocks); ``reduce`` (each task sums its inputs in a fixed order with
:func:`mmflow.workflow.engine.reduce.ordered_tree_sum`, so results are bit-identical on any cluster);
``solve`` (solve-then-apply: tasks solve over intervals independent of storage chunks and
write small solution stores; ``apply(ctx, block)`` corrects data where they are next read,
so a correction can never be applied twice and ``vis.zarr`` is never rewritten; a solve
stage may also have ``next_cycle`` for a second phase, e.g. a fit to the first phase's sums);
``iterative`` (``next_cycle(ctx, cycle) -> keys or None``: a loop of maps with a checkpoint
per cycle, resumable after a kill).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

#: what a stage can be (see above)
KINDS = ("map", "reduce", "solve", "iterative")


@dataclass(eq=False)
class Stage:
    """One step of the pipeline (compared and hashed by identity).

    ``reads_corrected``: the stage reads ``vis.zarr`` through every correction before it (the
    pipeline adds those solve stages' outputs to its ``inputs``). ``upstream``: the stages before
    it in its pipeline, set by :class:`mmflow.workflow.pipeline.Pipeline`; tasks find the
    producers of their inputs and the corrections to apply there.
    """

    name: str
    config: tuple
    inputs: tuple
    outputs: tuple
    prepare: Callable
    task: Optional[Callable]
    finalize: Optional[Callable] = None
    enabled: Callable = field(default=lambda cfg: True)
    description: str = ""
    kind: str = "map"
    files: Callable = field(default=lambda cfg: [])
    apply: Optional[Callable] = None
    next_cycle: Optional[Callable] = None
    counters: tuple = ()  # numeric fields of the tasks' infos summed, stored and logged per stage
    check: Optional[Callable] = None  # check(cfg, names of the stages this run executes), before any work
    scan: Optional[Callable] = None  # scan(cfg): reads the input data, before any work, when the stage has any
    reads_corrected: bool = False
    cost: Optional[object] = None  # its cost model (mmflow.workflow.plan.work.Cost: work, shrink settings)
    #: ``{store: (array attributes)}``: the arrays it reads of an input store of which it reads only some
    #: (:data:`mmflow.io.run_stores.ARRAYS` names; a store not named: all its arrays). What lets a large array
    #: go once its own readers have finished (:data:`mmflow.io.run_stores.RELEASED_ARRAYS`)
    reads: dict = field(default_factory=dict)
    #: the stage whose tasks of each channel run just before this stage's tasks of that channel (the keys of
    #: both carry ``freq``; :mod:`mmflow.workflow.engine.channels`): the runner alternates them channel by
    #: channel, and what that stage wrote for a channel (a group ``f{F}`` of a store this stage alone reads,
    #: released after it) goes once this stage has read it
    by_channel_after: Optional[str] = None
    #: ``{dimension: key field}``: each task reads the chunk of that index along ``dimension`` of the arrays
    #: :data:`mmflow.io.run_stores.RELEASED_BY_CHUNK` names, alone among the stage's tasks (mmodes:
    #: ``{"baseline": "bl_chunk"}``); where the stage is their last reader, a task's chunks are released once it
    #: has finished (:func:`mmflow.workflow.engine.release.release_task_chunks`)
    task_chunks: dict = field(default_factory=dict)
    #: False where its outputs are made from files outside the run (ingest): none of them is released, as
    #: a rerun could not make them again once those files are gone
    recomputable: bool = True
    upstream: tuple = field(default=(), repr=False)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"stage {self.name}: unknown kind {self.kind}")

    def producer_of(self, store, cfg):
        """The enabled earlier stage that writes ``store`` (None if none is enabled)."""
        return first_writer(self.upstream, store, cfg)

    def corrections(self, cfg):
        """The enabled solve-then-apply stages before this one, in pipeline order."""
        return [s for s in self.upstream if s.kind == "solve" and s.apply is not None and s.enabled(cfg)]


def first_writer(stages, store, cfg):
    """The first of ``stages`` that is enabled under ``cfg`` and writes ``store`` (None if none)."""
    return next((s for s in stages if store in s.outputs and s.enabled(cfg)), None)


def lazy_stage(package):
    """A module ``__getattr__`` for a stage package that imports its ``stage`` module on first use of
    ``STAGE``: the schema takes a stage's settings (``stages/<name>/settings.py``) without importing
    the stage, which imports the schema."""
    def __getattr__(name):
        if name == "STAGE":
            from importlib import import_module  # deferred: only when the stage itself is wanted

            return import_module(f"{package}.stage").STAGE
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
