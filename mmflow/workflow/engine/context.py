"""What every task needs, rebuilt cheaply in each worker process from the configuration.

A :class:`Context` is picklable (configuration as JSON, the absolute run directory and the
driver's lock token). ``ctx.for_stage(stage)`` gives a :class:`TaskContext`: the
configuration through the stage's :class:`~mmflow.workflow.engine.fingerprint.ConfigView`, verified
reads of input stores, and writes recorded (size and XXH3 checksum per chunk) for the completion
marker, with a non-finite guard on everything written.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import PurePath

import numpy as np
import zarr

from mmflow.errors import MmflowError
from mmflow.io.stores import ChunkLedger, open_checked
from mmflow.telescope import Telescope
from mmflow.telescope.beam_factory import make_beam
from mmflow.telescope.layout import Layout, selected_layout
from mmflow.workflow.config.schema import WorkflowConfig
from mmflow.workflow.engine.fingerprint import ConfigView
from mmflow.workflow.engine.geometry import run_freqs_hz
from mmflow.workflow.engine.rundir import RunDir
from mmflow.io.run_stores import STORES


class NonFiniteOutputError(MmflowError):
    """A stage was about to write NaN or inf."""


@dataclass(frozen=True)
class Context:
    """Picklable handle: the configuration (as JSON), the run directory and the lock token."""

    config_json: str
    run_path: str
    token: str = None

    @property
    def cfg(self) -> WorkflowConfig:
        return _parse(self.config_json)

    @property
    def run(self) -> RunDir:
        return RunDir(self.run_path)

    def for_stage(self, stage):
        return TaskContext(self.config_json, self.run_path, self.token, stage)


@dataclass(frozen=True)
class TaskContext(Context):
    """A context bound to one stage (and, inside a task, to that task's chunk records)."""

    stage: object = None
    ledger: ChunkLedger = field(default=None, compare=False)
    #: a task's opened groups and looked-up arrays (None: not kept). Each zarr open or lookup reads
    #: metadata through zarr's I/O thread (~1-1.5 ms); a task that reads and writes several arrays
    #: would otherwise repeat them. Only a stage task keeps them: it changes no store's metadata.
    handles: dict = field(default=None, compare=False, repr=False)

    @property
    def cfg(self):
        return ConfigView(_parse(self.config_json), self.stage.config, self.stage.name)

    def for_task(self, keep_handles=False):
        """A context with its own chunk records; ``keep_handles``: a stage task's (see ``handles``)."""
        return TaskContext(self.config_json, self.run_path, self.token, self.stage, ChunkLedger(self.run_path),
                           {} if keep_handles else None)

    # ------------------------------------------------------------------ stores
    def create(self, spec):
        """Create (or validate) one of this stage's declared stores; constant arrays are recorded."""
        g = spec.create(self.run_path)
        if self.ledger is not None:
            for a in spec.arrays:
                if a.data is not None:
                    self.ledger.record(g[a.name], ())
        return g

    def producer(self, store):
        """The enabled earlier stage of the pipeline that wrote the input ``store`` (None if none)."""
        return self.stage.producer_of(store, _parse(self.config_json))

    def corrections(self):
        """The enabled solve-then-apply stages before this stage, in pipeline order (their ``apply``
        corrects the visibilities this stage reads: :func:`mmflow.workflow.engine.blocks.read_block`)."""
        return self.stage.corrections(_parse(self.config_json))

    def open(self, store, mode="r"):
        """A declared store, through a :class:`~mmflow.io.stores.CheckedStore`: writes are checksummed
        as they pass; reads of an input store are checked against its producer's chunk records."""
        if store not in self.stage.inputs and store not in self.stage.outputs:
            raise MmflowError(f"stage '{self.stage.name}' opens {store}, which it does not declare")
        if self.handles is not None and (store, mode) in self.handles:
            return self.handles[store, mode]
        producer = self.producer(store) if store in self.stage.inputs else None
        expected = None
        if producer is not None and producer.name != self.stage.name and mode == "r":
            if self.stage.by_channel_after == producer.name and self.run.completion(producer.name) is None:
                expected = self.run.finished_chunks(producer.name)  # run channel by channel: its done tasks'
            else:
                expected = self.run.chunk_index(producer.name)
        g = open_checked(self.run_path, store, mode, expected, producer.name if producer else None)
        if self.handles is not None:
            self.handles[store, mode] = g
        return g

    def array(self, group, name):
        """``group[name]`` (kept with the group in a stage task: see ``handles``)."""
        if self.handles is None:
            return group[name]
        key = ("array", id(group), name)
        if key not in self.handles:
            self.handles[key] = (group, group[name])  # the group held: its id stays its own
        return self.handles[key][1]

    def read(self, array, region=()):
        """Read ``array[region]`` (a declared array, ``STORES.gains.gains``: it names its store); every
        chunk is checked against the producer's records as it is read."""
        g = self.open(array.store)
        arr = self.array(g, array)
        before = g.store.seconds
        try:
            return arr[tuple(region) if region else ...]
        finally:
            if self.ledger is not None:
                self.ledger.seconds += g.store.seconds - before

    def write(self, group, name, region, data, allow_nan=False):
        """Write a chunk-aligned region of array ``name`` (its handle, ``STORES.gains.gains``) of the open
        ``group``, refusing NaN/inf, and record its chunks."""
        store = getattr(name, "store", None)
        if store is not None and PurePath(str(group.store.root)).name != store:
            raise MmflowError(f"stage '{self.stage.name}' writes {store}'s array '{name}' into {group.store.root}")
        data = np.asarray(data)
        if not allow_nan:
            self.check_finite(f"{group.store.root}/{name} region {_fmt(region)}", data)
        self.ledger.write(group, name, region, data, arr=self.array(group, name))

    def check_finite(self, what, data):
        """Refuse NaN/inf about to be written (timed: the guard's cost is reported per stage)."""
        t0 = time.perf_counter()
        # one reduction propagates any NaN/inf (exact check only if the sum is not finite)
        finite = data.dtype.kind not in "fc" or bool(np.isfinite(np.sum(data))) or bool(np.isfinite(data).all())
        if self.ledger is not None:
            self.ledger.guard_seconds += time.perf_counter() - t0
        if not finite:
            bad = int(np.size(data) - np.count_nonzero(np.isfinite(data)))
            raise NonFiniteOutputError(
                f"stage '{self.stage.name}' was about to write {bad} NaN/inf values to {what}. Nothing was "
                "written; this is a bug or bad input upstream: check the inputs this stage read "
                "(mmflow verify RUN_DIR)")

    # ------------------------------------------------------------------ the array
    def telescope(self) -> Telescope:
        """The telescope as stored with the visibilities (layout, baselines, frequencies), beam
        from ``beam`` (stages that call this declare ``beam``)."""
        return _telescope(self.cfg.beam.model_dump_json(), self.run_path)

    def vis_attrs(self):
        return zarr.open_group(str(self.run.store(STORES.vis)), mode="r").attrs.asdict()


def _fmt(region):
    return "[" + ", ".join(f"{s.start}:{s.stop}" if isinstance(s, slice) else str(s) for s in region) + "]"


@lru_cache(maxsize=8)
def _parse(js):
    return WorkflowConfig.model_validate_json(js)


@lru_cache(maxsize=8)
def _telescope(beam_json, run_path):
    g = zarr.open_group(str(RunDir(run_path).store(STORES.vis)), mode="r")
    a = g.attrs.asdict()
    layout = Layout(a["antenna_names"], np.asarray(g[STORES.vis.antenna_enu][:]), a["lat_deg"], a["lon_deg"],
                    a["height_m"], a.get("layout_provenance", ""))
    tel = Telescope(layout, make_beam(json.loads(beam_json)), np.asarray(g[STORES.vis.freqs_hz][:]),
                    a["integration_s"], True, a.get("channel_width_hz", 0.0))
    tel.pairs = np.asarray(g[STORES.vis.pairs][:])
    return tel


def run_telescope(cfg, run_path):
    """The telescope stored with a run's visibilities (as :meth:`TaskContext.telescope`), outside a stage."""
    return _telescope(cfg.beam.model_dump_json(), str(run_path))


def build_telescope(cfg, ingest=None):
    """Telescope from the config (``telescope``, ``beam``, ``observation``), or for ingested data from
    ``ingest`` (the ingest plan, or a record's copy: its ``layout`` and ``freqs_hz``); its channels are
    :func:`mmflow.workflow.engine.geometry.run_freqs_hz`."""
    t = cfg.telescope
    layout = None if ingest is None else ingest.layout
    if layout is None:
        _, layout = selected_layout(t.preset, t.layout_file, t.lat_deg, t.lon_deg, t.radius_m, t.stands,
                                    t.max_antennas)
    return Telescope(layout, make_beam(cfg.beam.model_dump()), run_freqs_hz(cfg, ingest),
                     cfg.observation.integration_s, t.include_autos, cfg.observation.channel_width_khz * 1e3)
