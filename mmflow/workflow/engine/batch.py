"""SLURM/PBS worker jobs seen from the driver: job shapes, node sizes, queue states, lost jobs.

A dask-jobqueue cluster submits one batch job per worker (or per ``processes`` workers). This
module sizes those jobs (:func:`job_options`: what ``cluster.jobqueue`` leaves out, from the plan
and the partition's nodes), refuses a job no node of the partition can hold before anything is
submitted (:func:`refuse_impossible`), and watches the jobs while a run waits for workers
(:class:`JobWatch`): queued jobs are not dead workers, a worker that cannot reach the scheduler
is reported with its own error, and a lost job is logged and replaced.
"""
from __future__ import annotations

import ipaddress
import json
import math
import os
import re
import shlex
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

from mmflow.errors import InputError

#: what every worker imports when it starts (:mod:`mmflow.workflow.engine.worker_start`: the stages and the
#: compiled kernels), a local cluster's fork server and a job-queue worker's ``--preload`` alike
WORKER_PRELOAD = "mmflow.workflow.engine.worker_start"

#: a job's share of its walltime kept free at the end: workers retire before it
RETIRE_FRACTION = 0.2
#: seconds a job's worker may take to join the scheduler before it exits (``dask worker --death-timeout``)
#: where neither ``cluster.jobqueue`` nor dask's jobqueue.yaml sets another than dask-jobqueue's 60 s: a
#: preloaded worker (the stages, numba's kernels, astropy's tables) took over 60 s to start with six
#: starting on two busy cores, and died before it joined. A worker that cannot reach the scheduler
#: reports its error when this runs out, so it is not made longer than a few minutes.
DEATH_TIMEOUT_S = 180
#: dask-jobqueue's own ``death-timeout`` (its jobqueue.yaml): read as "not chosen"
JOBQUEUE_DEATH_TIMEOUT_S = 60
#: the job script's variable that holds the job's start (Unix seconds): a worker's lifetime counts from it
JOB_START_VAR = "MMFLOW_JOB_START"
#: lines of a worker's log that say why it could not reach the scheduler
CONNECT_ERROR = re.compile(r"(OSError|Timed out|timed out|unreachable|refused|Could not connect|CommClosedError)")


def _call(argv, timeout=15):
    """stdout of a batch-system command, or None where it is missing or fails."""
    try:
        r = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return r.stdout if r.returncode == 0 else None


def node_sizes(kind, queue=None):
    """``[(cpus, memory_mb), ...]`` of the nodes of SLURM partition ``queue`` (default partition
    when None), from ``sinfo``; None where it cannot be asked (PBS, no ``sinfo``)."""
    if kind != "slurm":
        return None
    out = _call(["sinfo", "-h", "-N", "-o", "%c %m"] + (["-p", queue] if queue else []))
    if out is None:
        return None
    sizes = []
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[0].isdigit() and parts[1].rstrip("+").isdigit():
            sizes.append((int(parts[0]), int(parts[1].rstrip("+"))))
    return sizes or None


def cluster_interface(kind):
    """This machine's interface on the network of the partition's nodes (``sinfo``'s NodeAddr
    inside the interface's IPv4 network) as ``(name, address)``; None where no node address
    is on a network of this machine (nodes behind a router) or the batch system cannot be asked."""
    import psutil  # deferred: a dependency of distributed, needed only by SLURM/PBS clusters

    if kind != "slurm":
        return None
    out = _call(["sinfo", "-h", "-N", "-o", "%o"])
    if not out:
        return None
    nodes = []
    for name in sorted(set(out.split())):
        try:
            nodes.append(ipaddress.ip_address(socket.gethostbyname(name)))
        except (OSError, ValueError):
            continue
    for iface, addrs in sorted(psutil.net_if_addrs().items()):
        for a in addrs:
            if a.family != socket.AF_INET or not a.netmask:
                continue
            net = ipaddress.ip_network(f"{a.address}/{a.netmask}", strict=False)
            if not net.is_loopback and any(n in net for n in nodes):
                return iface, a.address
    return None


def jobqueue_default(kind, key):
    import dask  # deferred: dask takes 0.3-0.8 s to import; only clusters need it

    return dask.config.get(f"jobqueue.{kind}.{key.replace('_', '-')}", None)


def _seconds(walltime):
    """SLURM/PBS walltime (``[D-]HH:MM:SS``, ``MM:SS``, minutes) in seconds; None if unreadable."""
    if walltime is None:
        return None
    text = str(walltime)
    days = 0
    if "-" in text:
        d, text = text.split("-", 1)
        days = int(d)
    try:
        parts = [int(p) for p in text.split(":")]
    except ValueError:
        return None
    if len(parts) == 1:
        parts = [0, parts[0], 0]  # SLURM: a bare number is minutes
    while len(parts) < 3:
        parts.insert(0, 0)
    h, m, s = parts[-3:]
    return days * 86400 + h * 3600 + m * 60 + s


def lifetime_args(walltime):
    """``dask worker`` options that retire a worker before its job's walltime: ``--lifetime`` a
    :data:`RETIRE_FRACTION` of it short (at least 20 s, at most 10 min or half the walltime),
    staggered by a quarter of that so that the workers of jobs started together do not all leave
    at once; ``[]`` when the walltime is unknown. dask counts the lifetime from the worker's start,
    which comes seconds to minutes into its job (Python's imports on a shared filesystem, the
    preload); a job's workers count it from the job's start instead (:data:`JOB_START_VAR`,
    :func:`mmflow.workflow.engine.worker_start.dask_setup`)."""
    total = _seconds(walltime)
    if not total:
        return []
    # a worker starts some seconds into its job and takes some to close: at least 20 s to spare
    margin = min(600.0, total / 2, max(RETIRE_FRACTION * total, 20.0))
    return ["--lifetime", f"{max(total - margin, 1):.0f}s", "--lifetime-stagger", f"{margin / 4:.0f}s"]


def largest_task_gb(cfg):
    """The plan's largest task of any enabled stage with a worker's baseline (GB)."""
    from mmflow.workflow.plan import planner as planmod  # deferred: the plan imports every stage
    from mmflow.workflow.pipeline import PIPELINE  # deferred: as the plan above

    names = [st.name for st in PIPELINE if st.enabled(cfg) and st.task is not None]
    costs = planmod.load_costs()
    g = planmod.geometry(cfg)
    ests = [planmod.estimate(n, g, cfg, costs, costs["sgemm_gflops"], 1) for n in names]
    return max((e.task_bytes for e in ests), default=0) / 1e9 + planmod.WORKER_BASE_BYTES / 1e9


def job_options(cfg, kind, log=print, opts=None):
    """``cluster.jobqueue`` (or ``opts``: it with a pool's shape, :mod:`mmflow.workflow.engine.pools`)
    with what it leaves out filled in, ready for dask-jobqueue.

    * cores and memory, when neither ``cluster.jobqueue`` nor dask's jobqueue.yaml gives them:
      ``cluster.threads_per_worker`` cores and 1.5x the plan's largest task and the job's own ``dask worker``
      process (:data:`mmflow.workflow.plan.nodes.JOB_PROCESS_BYTES`; at least 2 GB), capped
      at the largest node of the partition (``sinfo``);
    * ``log_directory``: ``<run.directory>/cluster-logs`` (the driver reads the workers' errors
      there); ``$USER``-style variables expanded in it and in ``local_directory`` (``#SBATCH``
      lines are not expanded by SLURM);
    * ``death_timeout`` :data:`DEATH_TIMEOUT_S` where dask-jobqueue's 60 s stands;
    * ``--lifetime``/``--lifetime-stagger`` for the workers from the walltime (:func:`lifetime_args`),
      unless ``worker_extra_args`` sets a lifetime;
    * ``--preload`` :data:`WORKER_PRELOAD`: each worker loads the stages and numba's kernels when it starts,
      as a local cluster's forked workers have them, not inside its first task (whose memory the plan
      then reads as the task's: a fresh worker's first m-mode task traced 0.058 GB against 0.019 planned).
    """
    from dask.utils import format_bytes, parse_bytes  # deferred: as in jobqueue_default

    c = cfg.cluster
    opts = dict(c.jobqueue if opts is None else opts)
    sizes = node_sizes(kind, opts.get("queue") or jobqueue_default(kind, "queue"))
    filled = []
    if opts.get("cores") is None and jobqueue_default(kind, "cores") is None:
        opts["cores"] = c.threads_per_worker
        filled.append(f"cores {opts['cores']}")
    if opts.get("memory") is None and jobqueue_default(kind, "memory") is None:
        from mmflow.workflow.plan.nodes import JOB_PROCESS_BYTES  # deferred: as largest_task_gb's plan

        task = largest_task_gb(cfg)
        gb = max(2.0, math.ceil((1.5 * task + JOB_PROCESS_BYTES / 1e9) * 2) / 2)
        if sizes:
            gb = min(gb, max(m for _, m in sizes) * 2 ** 20 / 1e9)
        opts["memory"] = format_bytes(int(gb * 1e9)).replace(" ", "")
        filled.append(f"memory {opts['memory']} (the plan's largest task {task:.2f} GB x1.5 and the job's own "
                      f"process {JOB_PROCESS_BYTES / 1e9:.2f} GB, at least 2 GB"
                      + (", at most a node's" if sizes else "") + ")")
    if opts.get("processes") is None and jobqueue_default(kind, "processes") is None:
        opts["processes"] = 1
    if opts.get("death_timeout") is None and \
            jobqueue_default(kind, "death_timeout") in (None, JOBQUEUE_DEATH_TIMEOUT_S):
        opts["death_timeout"] = DEATH_TIMEOUT_S
    if filled:
        log(f"cluster.jobqueue: {', '.join(filled)} per job (set cluster.jobqueue.cores/memory to choose)")
    for key in ("log_directory", "local_directory"):
        if opts.get(key):
            opts[key] = os.path.expandvars(os.path.expanduser(str(opts[key])))
    if not opts.get("log_directory") and not jobqueue_default(kind, "log_directory"):
        opts["log_directory"] = str(Path(cfg.run.directory).expanduser().absolute() / "cluster-logs")
    extra = list(opts.get("worker_extra_args") or jobqueue_default(kind, "worker_extra_args") or [])
    if not any(a.startswith("--lifetime") for a in extra):
        extra += lifetime_args(opts.get("walltime") or jobqueue_default(kind, "walltime"))
    if WORKER_PRELOAD not in extra:
        extra += ["--preload", WORKER_PRELOAD]
    opts["worker_extra_args"] = extra
    parse_bytes(str(opts["memory"] or jobqueue_default(kind, "memory")))  # a bad size fails here, not in a job
    return opts, sizes


def refuse_impossible(opts, kind, sizes):
    """Refuse a job that no node of the partition can hold (``sinfo``), before any submission:
    SLURM's default ``EnforcePartLimits=NO`` accepts it and it pends (``PartitionConfig``) forever."""
    from dask.utils import parse_bytes  # deferred: as in job_options

    if not sizes:
        return
    cores = int(opts.get("cores") or jobqueue_default(kind, "cores") or 1)
    mem_mb = parse_bytes(str(opts.get("memory") or jobqueue_default(kind, "memory"))) / 2 ** 20
    part = opts.get("queue") or jobqueue_default(kind, "queue") or "the default partition"
    if any(cpus >= cores and mb >= mem_mb for cpus, mb in sizes):
        return
    max_cpus, max_mb = max(s[0] for s in sizes), max(s[1] for s in sizes)
    if cores > max_cpus:
        raise InputError("cluster", "cluster.jobqueue.cores", f"a job asks for {cores} cores, more than any node "
                         f"of {part} has (at most {max_cpus} CPUs, sinfo): it would wait in the queue forever",
                         f"set cluster.jobqueue.cores <= {max_cpus} (and processes to match)")
    raise InputError("cluster", "cluster.jobqueue.memory", f"a job asks for {mem_mb / 1024:.1f} GiB, more than any "
                     f"node of {part} with {cores} CPUs has (at most {max_mb / 1024:.1f} GiB, sinfo): it would wait "
                     "in the queue forever", f"set cluster.jobqueue.memory <= {max_mb}MiB, or a partition "
                     "of larger nodes (cluster.jobqueue.queue)")


#: PBS job states (``job_state``, qstat's ``S`` column) as JobWatch counts them (SLURM's words): a job
#: exiting after its run (E) still holds its node, as SLURM's COMPLETING
PBS_STATES = {"Q": "PENDING", "H": "PENDING", "W": "PENDING", "T": "PENDING", "R": "RUNNING", "E": "RUNNING",
              "S": "SUSPENDED", "U": "SUSPENDED", "B": "RUNNING", "F": "COMPLETED", "C": "COMPLETED", "X": "COMPLETED"}


def _pbs_id(text):
    """A PBS job id without its server (``'8.scheduler'`` -> ``'8'``)."""
    return text.split(".")[0]


def parse_qstat_json(text, ids):
    """``{job id: (state, reason, node)}`` of the jobs ``ids`` from ``qstat -f -F json`` (OpenPBS, PBS Pro):
    the state in SLURM's words (:data:`PBS_STATES`), the reason the scheduler's ``comment`` (e.g. "Not
    Running: Insufficient amount of resource: ncpus"), the node the first of ``exec_host``.

    Raises
    ------
    ValueError, TypeError
        ``text`` is not that JSON (None, or Torque's qstat, which has no ``-F json``).
    """
    jobs = json.loads(text)["Jobs"] if text else None
    if not isinstance(jobs, dict):
        raise TypeError("no Jobs in qstat's JSON")
    out = {}
    for full, job in jobs.items():
        if _pbs_id(full) in ids:
            code = job.get("job_state", "")
            reason = job.get("comment") or {"H": "held"}.get(code, "queued")
            out[_pbs_id(full)] = (PBS_STATES.get(code, code), reason, (job.get("exec_host") or "").split("/")[0])
    return out


def parse_qstat(text, ids):
    """``{job id: (state, reason, node)}`` of the jobs ``ids`` from plain ``qstat`` (Torque, and PBS without
    ``-F json``): columns job id, name, user, time use, state, queue; no reason (``'queued'``) nor node."""
    out = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) >= 6 and _pbs_id(parts[0]) in ids:
            out[_pbs_id(parts[0])] = (PBS_STATES.get(parts[4], parts[4]), {"H": "held"}.get(parts[4], "queued"), "")
    return out


@dataclass
class QueueState:
    """What the batch system says about a run's worker jobs (:meth:`JobWatch.poll`)."""

    pending: list = field(default_factory=list)  # (job id, reason)
    running: list = field(default_factory=list)  # job ids started, their worker not (yet) joined: starting
    fatal: str | None = None  # why no worker can join (one could not reach the scheduler: its own error)

    def waiting(self):
        """``'waiting for N queued jobs (reason)'``, or None when no job is queued."""
        if not self.pending:
            return None
        reasons = sorted({r for _, r in self.pending})
        return f"waiting for {len(self.pending)} queued jobs ({', '.join(reasons)})"


class JobWatch:
    """The worker jobs of a dask-jobqueue cluster, as the scheduler and the batch system see them.

    :meth:`poll` asks ``squeue`` (SLURM; ``qstat`` for PBS) at most every ``interval`` s, logs a
    worker that was lost (its job ended or its worker left) and scales the cluster back to
    ``n_jobs`` so that dask-jobqueue submits a replacement.

    Parameters
    ----------
    cluster : dask_jobqueue.JobQueueCluster
    kind : {'slurm', 'pbs'}
    n_jobs : int
        Jobs the run asks for (``cluster.n_workers``).
    log_directory : str or None
        Where the jobs write their logs (``<name>-<job id>.err``).
    """

    def __init__(self, cluster, kind, n_jobs, log_directory, interval=2.0, log=print, pools=None):
        self.cluster, self.kind, self.n_jobs = cluster, kind, n_jobs
        self.pools = pools  # a :class:`mmflow.workflow.engine.pools.StagePools` where jobs are sized per stage
        self.retired = set()  # jobs retired when the run moved to another pool: not lost, not replaced
        self.log_directory = Path(log_directory) if log_directory else None
        self.interval, self.log = interval, log
        self.connected = {}  # job name -> job id of a job whose worker joined the scheduler
        self.started = {}  # job id -> time it was first seen running
        self.last, self.state, self.failed_starts = 0.0, QueueState(), 0
        self.left = set()  # jobs whose worker left the scheduler (logged once)
        self.scaled = time.time()  # the cluster was scaled when it started
        self.node_of = {}  # job id -> the node it ran on

    def _jobs(self):
        return {name: job.job_id for name, job in list(self.cluster.workers.items())
                if getattr(job, "job_id", None) and name not in self.retired}

    def retire(self, names):
        """Forget the jobs ``names`` (retired on purpose: the run moved to another pool)."""
        self.retired |= set(names)
        for name in names:
            self.connected.pop(name, None)
            self.left.discard(name)

    def _queue(self, ids):
        """``{job id: (state, reason, node)}`` of the jobs the batch system still lists."""
        if not ids:
            return {}
        if self.kind == "slurm":
            out = _call(["squeue", "-h", "-o", "%i|%T|%r|%N", "-j", ",".join(ids)]) or ""
            rows = [line.split("|") for line in out.splitlines() if line.count("|") == 3]
            return {i: ("RUNNING" if s in ("RUNNING", "COMPLETING") else s, r, n) for i, s, r, n in rows}
        text = _call(["qstat", "-f", "-F", "json", *ids])  # OpenPBS / PBS Pro: the scheduler's comment too
        try:
            return parse_qstat_json(text, ids)
        except (TypeError, ValueError):  # Torque: no -F json
            return parse_qstat(_call(["qstat", *ids]) or "", ids)

    def error_in_log(self, job_id):
        """The last line of a job's log that says it could not reach the scheduler, or None."""
        if self.log_directory is None:
            return None
        for path in sorted(self.log_directory.glob(f"*-{job_id}.err")) + sorted(self.log_directory.glob(f"*{job_id}*")):
            try:
                lines = path.read_text(errors="replace").splitlines()
            except OSError:
                continue
            hits = [ln.strip() for ln in lines if CONNECT_ERROR.search(ln)]
            if hits:
                cause = next((h for h in hits if "Errno" in h and h != hits[-1]), None)  # e.g. Connection refused
                return f"{hits[-1]}{f' ({cause})' if cause else ''} (log: {path})"
        return None

    def poll(self, client, force=False):
        """The jobs' :class:`QueueState`, asking the batch system at most every ``interval`` s."""
        now = time.time()
        if not force and now - self.last < self.interval:
            return self.state
        self.last = now
        jobs = self._jobs()
        for name, job_id in self.connected.items():  # a job dask-jobqueue itself closed after its worker left
            jobs.setdefault(name, job_id)
        joined = {str(w.get("name")) for w in client.scheduler_info().get("workers", {}).values()}
        queue = self._queue(list(jobs.values()))
        st = QueueState()
        for name, job_id in jobs.items():
            state, reason, node = queue.get(job_id, ("GONE", "", ""))
            if node and state == "RUNNING":
                self.node_of[job_id] = node  # kept once the job has ended
            node = self.node_of.get(job_id, "")
            where = f" on {node}" if node else ""
            if any(w == name or w.startswith(f"{name}-") for w in joined):
                self.connected[name] = job_id
                self.left.discard(name)
            elif name in self.connected:
                if name not in self.left:
                    self.left.add(name)
                    self.log(f"worker of job {job_id}{where} lost: it left the scheduler (job {state.lower()} per "
                             f"{'squeue' if self.kind == 'slurm' else 'qstat'}); its tasks go to the other workers")
                if state == "RUNNING" and name in self.cluster.workers:
                    continue  # dask-jobqueue cancels the job after its lost-worker timeout
                self.log(f"worker job {job_id}{where} "
                         + ("cancelled after its worker was lost" if state == "RUNNING" else f"ended ({state.lower()})")
                         + ": submitting a replacement")
                del self.connected[name]
                self.left.discard(name)
                self._drop(name, job_id)
            elif state == "PENDING":
                st.pending.append((job_id, "just submitted" if reason in ("", "None") else reason))
            elif state == "RUNNING":
                self.started.setdefault(job_id, now)
                st.running.append(job_id)
                err = self.error_in_log(job_id) if now - self.started[job_id] > 10 else None
                if err and not joined:
                    st.fatal = self._unreachable(client, job_id, err)
            elif name in self.cluster.workers:  # ended without its worker ever joining
                err = self.error_in_log(job_id)
                self.failed_starts += 1
                if err and not joined:
                    st.fatal = self._unreachable(client, job_id, err)
                elif self.failed_starts > 2 * self.n_jobs and not self.connected:
                    st.fatal = (f"{self.failed_starts} worker jobs ended before their worker joined (last: job "
                                f"{job_id}{': ' + err if err else ''}). Fix: read the jobs' logs in "
                                f"{self.log_directory}")
                if st.fatal:
                    continue
                self.log(f"worker job {job_id}{where} ended ({state.lower()}) before its worker joined"
                         + (f": {err}" if err else "") + "; submitting a replacement")
                self._drop(name, job_id)
        if len(self.cluster.workers) < self.n_jobs:  # dask-jobqueue closed a lost job itself
            self._scale()
        self.state = st
        return st

    def _drop(self, name, job_id):
        """Cancel and forget a dead job (one the batch system requeued too) so that scaling to
        ``n_jobs`` submits a new one in its place."""
        _call([*shlex.split(self.cluster._dummy_job.cancel_command), job_id])
        self.cluster.workers.pop(name, None)
        self.cluster.worker_spec.pop(name, None)
        # a new name: dask's own handling of the lost worker closes whatever job holds the old one
        self.cluster._i = getattr(self.cluster, "_i", 0) + 1
        self._scale(force=True)

    def _scale(self, force=False):
        """Scale to ``n_jobs``: dask-jobqueue submits the jobs missing (at most every 10 s unless
        ``force``: a submission in flight is not yet among the cluster's jobs)."""
        if force or time.time() - self.scaled > 10:
            self.scaled = time.time()
            self.cluster.scale(jobs=self.n_jobs)

    def _unreachable(self, client, job_id, err):
        return (f"worker job {job_id} could not reach the scheduler at {client.scheduler.address}: {err}. "
                "Fix: set cluster.interface to the network interface the compute nodes share with this machine "
                "(`ip -br addr` lists them; docs/clusters.md)")


