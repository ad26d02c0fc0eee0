"""The pipeline: the stages of a run, in order, in one list.

Everything that depends on the order derives from :data:`PIPELINE`: the runner's loop, the
``mmflow <stage>`` subcommands, the planner, the corrections a stage's reads apply
(:meth:`mmflow.workflow.stages.base.Stage.corrections`: the enabled solve-then-apply stages
before it) and the correction stores a ``reads_corrected`` stage declares as inputs. Tests
build their own :class:`Pipeline` (a toy stage in place of one) and pass it to
:func:`mmflow.workflow.engine.runner.run_workflow`.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

from importlib import import_module

from mmflow.io.run_stores import RELEASED_ARRAYS, RELEASED_BY_DEFAULT, STORES
from mmflow.workflow.stages import ORDER
from mmflow.workflow.stages.base import first_writer

_NAMED = {}


@dataclass(frozen=True)
class Pipeline:
    """Stages in run order, each knowing the stages before it (``Stage.upstream``).

    Build with :meth:`of`; a pipeline registered under a name (:func:`register`) pickles as that
    name, so dask tasks carry a reference rather than every stage's functions.
    """

    stages: tuple
    name: str = None

    @classmethod
    def of(cls, *stages, name=None):
        """The pipeline of ``stages`` in this order: each gets its ``upstream`` (the stages before it),
        and a ``reads_corrected`` stage the outputs of the solve-then-apply stages before it as inputs."""
        names = [s.name for s in stages]
        if len(set(names)) != len(names):
            raise ValueError(f"a stage appears twice in the pipeline {names}")
        built = []
        for s in stages:
            up = tuple(built)
            inputs = s.inputs
            if s.reads_corrected:
                inputs += tuple(o for u in up if u.kind == "solve" and u.apply is not None for o in u.outputs
                                if o not in inputs)
            built.append(replace(s, upstream=up, inputs=inputs))
        return cls(tuple(built), name)

    def replace(self, *stages):
        """A new (unnamed) pipeline with ``stages`` in place of the stages of the same names."""
        new = {s.name: s for s in stages}
        unknown = set(new) - set(self.names)
        if unknown:
            raise KeyError(f"no stage {sorted(unknown)} in the pipeline")
        return Pipeline.of(*(new.get(s.name, s) for s in self.stages))

    @property
    def names(self):
        return tuple(s.name for s in self.stages)

    def __iter__(self):
        return iter(self.stages)

    def __len__(self):
        return len(self.stages)

    def stage(self, name):
        """The stage called ``name``."""
        for s in self.stages:
            if s.name == name:
                return s
        raise KeyError(f"no stage '{name}' in the pipeline (stages: {', '.join(self.names)})")

    def producer_of(self, store, cfg):
        """The enabled stage that writes ``store`` (None if none is enabled)."""
        return first_writer(self.stages, store, cfg)

    def declared_readers(self, store):
        """The stages that read ``store``: those that declare it as an input (``Stage.inputs``, the one place
        a store's readers are written; a ``reads_corrected`` stage reads the corrections before it), its
        writers excluded."""
        return [s for s in self.stages if store in s.inputs and store not in s.outputs]

    def readers(self, store, cfg):
        """The :meth:`declared_readers` of ``store`` enabled under ``cfg``."""
        return [s for s in self.declared_readers(store) if s.enabled(cfg)]

    def array_readers(self, store, array, cfg):
        """The enabled stages that read array ``array`` (its :data:`mmflow.io.run_stores.ARRAYS` attribute) of
        ``store``: its :meth:`readers` less those that read only other arrays of it (``Stage.reads``)."""
        return [s for s in self.readers(store, cfg) if store not in s.reads or array in s.reads[store]]

    def lifetimes(self):
        """``{store: (writers, readers, released, arrays)}`` of every store (:data:`mmflow.io.run_stores.STORES`):
        the names of the stages that write it and read it, whether it is released once its readers have
        finished (:data:`mmflow.io.run_stores.RELEASED_BY_DEFAULT`), and ``{array: readers}`` of its arrays
        released alone (:data:`mmflow.io.run_stores.RELEASED_ARRAYS`); for ``docs/stores.md``."""
        return {store: (tuple(s.name for s in self.stages if store in s.outputs),
                        tuple(s.name for s in self.declared_readers(store)), store in RELEASED_BY_DEFAULT,
                        {a: tuple(s.name for s in self.declared_readers(store) if store not in s.reads
                                  or a in s.reads[store]) for a in RELEASED_ARRAYS.get(store, ())})
                for store in STORES}

    def released(self, cfg):
        """``{store: stage}``: the intermediates this run releases (:data:`mmflow.io.run_stores.RELEASED_BY_DEFAULT`
        less ``run.keep``) that an enabled stage writes, each with the stage after which it goes: its last
        reader in pipeline order, or its writer where no other stage reads it (:meth:`release_point`)."""
        out = {}
        for store in RELEASED_BY_DEFAULT:
            writer = self.producer_of(store, cfg)
            if writer is None or not writer.recomputable or store in cfg.run.keep:
                continue
            out[store] = self.release_point((self.readers(store, cfg) or [writer])[-1], cfg)
        return out

    def release_point(self, stage, cfg):
        """The stage after which what goes after ``stage`` is released: ``stage``, or the enabled stage run
        channel by channel with it (``Stage.by_channel_after``: both complete together)."""
        return next((s.name for s in self.stages if s.by_channel_after == stage.name and s.enabled(cfg)),
                    stage.name)

    def released_arrays(self, cfg):
        """``{"store/array": stage}``: the arrays of :data:`mmflow.io.run_stores.RELEASED_ARRAYS` this run
        releases (their store not in ``run.keep``, nor released whole, its writer enabled and able to make it
        again: ``Stage.recomputable``), each with the stage after which it goes: its last reader
        (:meth:`array_readers`) in pipeline order, or its writer where no other stage reads it."""
        out = {}
        for store, arrays in RELEASED_ARRAYS.items():
            writer = self.producer_of(store, cfg)
            if writer is None or not writer.recomputable or store in cfg.run.keep or store in RELEASED_BY_DEFAULT:
                continue
            for array in arrays:
                out[f"{store}/{array}"] = self.release_point((self.array_readers(store, array, cfg) or [writer])[-1],
                                                             cfg)
        return out

    def __reduce__(self):
        if self.name is not None and _NAMED.get(self.name) is self:
            return named, (self.name,)
        return Pipeline, (self.stages, None)


def register(pipeline, name):
    """Register ``pipeline`` under ``name`` (it then pickles as a reference to the name)."""
    p = Pipeline(pipeline.stages, name)
    _NAMED[name] = p
    return p


def named(name):
    """The pipeline registered under ``name``."""
    return _NAMED[name]


#: the stages of an mmflow run, in order (:data:`mmflow.workflow.stages.ORDER`)
PIPELINE = register(Pipeline.of(*(import_module(f"mmflow.workflow.stages.{name}").STAGE for name in ORDER)), "mmflow")
