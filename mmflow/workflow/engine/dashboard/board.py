"""The run's state as the dashboard shows it: a small object the driver updates and the page reads.

The driver's thread writes (:meth:`RunBoard.begin_run`, :meth:`RunBoard.begin_stage`, ...), the
scheduler's event loop reads (:meth:`RunBoard.snapshot`); a lock keeps every read consistent. One
driver runs one workflow at a time, so a process has one board, :data:`BOARD`.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import asdict, dataclass

#: what a stage is doing: not begun, tasks running, finished in this run, finished before (kept), stopped
STATES = ("waiting", "running", "done", "kept", "stopped")


@dataclass
class StageRow:
    """One stage of the run: its plan and its progress.

    Attributes
    ----------
    name : str
    planned_tasks : int or None
        Tasks the plan expects (:func:`mmflow.workflow.plan.planner.stage_work`); None without a plan.
    task_seconds : float or None
        The plan's time of one task on one task slot (at the SGEMM rate the plan's constants were fitted at).
    task_gb : float or None
        The plan's memory of the stage's largest task with a worker's baseline (GB).
    total, done : int
        Tasks of the stage (known once it began; cycles of an iterative stage add theirs) and finished ones.
    state : str
        One of :data:`STATES`.
    started, wall_s : float or None
        When it began (``time.time()``) and how long it took once finished.
    """

    name: str
    planned_tasks: int | None = None
    task_seconds: float | None = None
    task_gb: float | None = None
    total: int | None = None
    done: int = 0
    state: str = "waiting"
    started: float | None = None
    wall_s: float | None = None
    batch_base: int = 0  # tasks done before the batch now running (a cycle, a second phase)

    def remaining(self):
        """Tasks left to run (the plan's count for a stage not yet begun)."""
        if self.state in ("done", "kept"):
            return 0
        total = self.total if self.total is not None else (self.planned_tasks or 0)
        return max(total - self.done, 0)


class RunBoard:
    """What the driver tells the dashboard about its run.

    Parameters
    ----------
    clock : callable
        Wall-clock seconds (``time.time``; tests pass their own).
    """

    def __init__(self, clock=time.time):
        self.clock = clock
        self._lock = threading.Lock()
        self._reset()

    def _reset(self):
        self.run_dir, self.cluster, self.slots, self.worker_base_gb = None, None, 1, None
        self.stages, self.started, self.ended, self.error = {}, None, None, None

    # -- the driver's side
    def begin_run(self, run_dir, cluster, stage_names, estimates=(), slots=1):
        """A run starts: its directory, the cluster's kind, its stages in pipeline order and their plan.

        Parameters
        ----------
        run_dir : str or Path
        cluster : str
            The cluster's kind (``local``, ``slurm``, ``pbs``, ``address``, ``synchronous``).
        stage_names : list of str
            The stages the run may run, in pipeline order.
        estimates : iterable of :class:`mmflow.workflow.plan.planner.StageEstimate`
            The plan of the stages still to run, each on one task slot (``check_fits``'s estimates).
        slots : int
            Tasks the cluster runs at once, as configured (the page uses the workers' threads once they came).
        """
        from mmflow.workflow.plan.planner import WORKER_BASE_BYTES  # deferred: the planner imports every stage

        plan = {e.stage: e for e in estimates}
        with self._lock:
            self._reset()
            self.run_dir, self.cluster, self.started = str(run_dir), cluster, self.clock()
            self.slots = max(int(slots), 1)
            self.worker_base_gb = WORKER_BASE_BYTES / 1e9
            for name in stage_names:
                e = plan.get(name)
                row = StageRow(name)
                if e is not None:
                    row.planned_tasks = int(e.tasks)
                    row.task_seconds = e.seconds / e.tasks if e.seconds and e.tasks else None
                    row.task_gb = (e.task_bytes + WORKER_BASE_BYTES) / 1e9
                self.stages[name] = row

    def _row(self, name):
        return self.stages.setdefault(name, StageRow(name))

    def begin_stage(self, name, total, done):
        """A stage begins with ``total`` tasks of which ``done`` finished in an earlier run."""
        with self._lock:
            r = self._row(name)
            r.total, r.done, r.batch_base = int(total), int(done), int(done)
            r.state, r.started = "running", self.clock()

    def keep_stage(self, name, total):
        """A stage finished before with the same settings: nothing of it runs."""
        with self._lock:
            r = self._row(name)
            r.total, r.done, r.state = int(total), int(total), "kept"

    def add_tasks(self, name, n, done=0):
        """A cycle (or a second phase) of a stage adds ``n`` tasks, ``done`` of them finished before."""
        with self._lock:
            r = self._row(name)
            r.total = (r.total or 0) + int(n)
            r.done += int(done)

    def begin_batch(self, name):
        """The driver sends a batch of the stage's tasks: :meth:`progress` counts from here."""
        with self._lock:
            r = self._row(name)
            r.batch_base = r.done

    def progress(self, name, batch_done):
        """``batch_done`` tasks of the batch sent last have finished."""
        with self._lock:
            r = self._row(name)
            r.done = r.batch_base + int(batch_done)

    def finish_stage(self, name, wall_s):
        """The stage is complete (every task and its finalize)."""
        with self._lock:
            r = self._row(name)
            r.state, r.wall_s = "done", float(wall_s)
            r.done = max(r.done, r.total or 0)

    def end_run(self, error=None, run_dir=None):
        """The run in ``run_dir`` ended: finished (``error`` None) or stopped with ``error`` (text). A run
        refused before it began (no :meth:`begin_run`) replaces the previous run's figures by its refusal."""
        with self._lock:
            if run_dir is not None and str(run_dir) != self.run_dir:
                self._reset()
                self.run_dir, self.started = str(run_dir), self.clock()
            self.ended, self.error = self.clock(), error
            for r in self.stages.values():
                if r.state == "running":
                    r.state = "stopped" if error else "done"

    # -- the page's side
    def snapshot(self):
        """A consistent copy: ``run_dir``, ``cluster``, ``slots``, ``worker_base_gb`` (the plan's baseline of a
        worker), ``started``, ``ended``, ``error``, ``now`` and ``stages`` (a list of :class:`StageRow` dicts in
        pipeline order)."""
        with self._lock:
            return {"run_dir": self.run_dir, "cluster": self.cluster, "slots": self.slots,
                    "worker_base_gb": self.worker_base_gb, "started": self.started,
                    "ended": self.ended, "error": self.error, "now": self.clock(),
                    "stages": [{k: v for k, v in asdict(r).items() if k != "batch_base"} for r in self.stages.values()]}


def seconds_left(snapshot, slots=None):
    """Time the run has left by its plan: per unfinished stage ``task_seconds x ceil(tasks left / slots)``.

    Parameters
    ----------
    snapshot : dict
        :meth:`RunBoard.snapshot`.
    slots : int, optional
        Tasks running at once (the workers' threads); default the configured ``snapshot['slots']``.

    Returns
    -------
    (float, list of str)
        The planned seconds, and the stages with tasks left whose time the plan does not know.
    """
    slots = max(int(slots or snapshot["slots"] or 1), 1)
    total, unknown = 0.0, []
    for r in snapshot["stages"]:
        left = StageRow(**r).remaining()
        if not left:
            continue
        if r["task_seconds"] is None:
            unknown.append(r["name"])
            continue
        total += r["task_seconds"] * math.ceil(left / slots)
    return total, unknown


def cluster_kind(client):
    """The kind of cluster a client runs on: ``synchronous`` (no client), the kind
    :func:`mmflow.workflow.engine.cluster.open_cluster` chose, or ``address`` for any other dask client."""
    if client is None:
        return "synchronous"
    return getattr(client, "kind", None) or "address"


#: the job options of a SLURM/PBS cluster that say what it ran on
JOB_OPTIONS = ("cores", "memory", "processes", "walltime", "queue", "account")


def cluster_record(cfg, client):
    """The cluster a run runs on, as ``run.json`` keeps it for the report (nothing is asked of the cluster,
    which starts only when the first task is sent): its kind and the shape the configuration gives it."""
    kind = cluster_kind(client)
    c = cfg.cluster
    if kind in ("synchronous", "address"):  # one process; a cluster made elsewhere, whose shape is not ours
        return {"kind": kind}
    if kind == "local":
        return {"kind": kind, "workers": c.n_workers, "threads_per_worker": c.threads_per_worker,
                "memory_limit": str(c.memory_limit)}
    job = dict(c.jobqueue or {})
    return {"kind": kind, "jobs": c.n_workers, "job": {k: job[k] for k in JOB_OPTIONS if job.get(k) is not None}}


#: the process's board: the runner writes it, the page reads it
BOARD = RunBoard()
