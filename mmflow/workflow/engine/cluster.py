"""Where the graph runs: a local cluster, an existing scheduler, or SLURM/PBS via dask-jobqueue.

A dask scheduler runs whatever code a client sends it, so a local cluster listens on the
loopback interface only (scheduler, workers and dashboard on 127.0.0.1); ``cluster.expose:
true`` opens them to the network (see docs/clusters.md for dask's TLS settings).
"""
from __future__ import annotations

import os
import socket
from contextlib import contextmanager

from mmflow.environ import restored_environ
from mmflow.errors import InputError
from mmflow.workflow.engine.batch import WORKER_PRELOAD, JobWatch, cluster_interface, job_options, refuse_impossible
from mmflow.workflow.engine.pools import StagePools, job_prologue, plan_pools, pool_options

LOOPBACK = "127.0.0.1"
ALL_INTERFACES = "0.0.0.0"


def bind_host(c):
    """The interface a local scheduler and dashboard listen on: loopback unless ``expose``."""
    return ALL_INTERFACES if c.expose else LOOPBACK


def dashboard_bind(c):
    """``cluster.dashboard_address`` with its host filled in (``':8787'`` -> ``'127.0.0.1:8787'``)."""
    host, _, port = c.dashboard_address.rpartition(":")
    return f"{host or bind_host(c)}:{port}"


def memory_limit(text):
    """``cluster.memory_limit`` as dask takes it: ``'auto'``, a fraction (float) or a byte string."""
    try:
        return float(text)
    except ValueError:
        return text


#: dask's setting for how a local cluster's nanny starts its worker process
START_METHOD = "distributed.worker.multiprocessing-method"
#: what a local worker's server process imports once, before it forks each worker
PRELOAD = ("distributed", WORKER_PRELOAD)


def fork_workers_from_a_preloaded_server():
    """Start local workers by forking a server process that imported mmflow's stages once.

    With dask's default (``spawn``) every local worker is a new interpreter that imports numpy,
    astropy, zarr and every stage (~3-5 s of CPU each, and again for every cluster a process
    opens). With ``forkserver`` a server process imports :data:`PRELOAD` once (the stages and the
    compiled imaging kernels: :mod:`mmflow.workflow.engine.worker_start`) and each worker is a fork of it
    (a cluster opened again in the same process starts in ~0.3 s instead of ~6 s).
    The server is started here with dask's pre-spawn environment (``distributed.nanny.pre-spawn-
    environ``: one BLAS/OpenMP thread, glibc's trim threshold; ``PYTHONHASHSEED``), which must be set
    before numpy loads and which dask's nanny would otherwise set only in a spawned child. A start
    method the user chose (the ``DASK_DISTRIBUTED__WORKER__MULTIPROCESSING_METHOD`` environment
    variable) is kept, as is dask's where Python has no ``forkserver`` (Windows). Idempotent; the
    server lives until this process exits.
    """
    import multiprocessing  # deferred: as the forkserver below
    import multiprocessing.forkserver as forkserver  # deferred: only local clusters start one

    import dask  # deferred: as distributed in open_cluster
    from distributed.utils import get_mp_context  # deferred: as above

    if ("DASK_DISTRIBUTED__WORKER__MULTIPROCESSING_METHOD" in os.environ
            or "forkserver" not in multiprocessing.get_all_start_methods()):  # Windows: spawn only
        return
    dask.config.set({START_METHOD: "forkserver"})
    get_mp_context().set_forkserver_preload(list(PRELOAD))
    env = {k: str(v) for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()}
    env.setdefault("PYTHONHASHSEED", "6640")  # as dask's nanny sets it for spawned workers
    with restored_environ(*env):
        os.environ.update(env)
        forkserver.ensure_running()


def interface_address(name):
    """The IPv4 address of this machine's network interface ``name``; an InputError naming the
    interfaces there are when it has none (``cluster.interface``, checked before any job is submitted)."""
    import psutil  # deferred: a dependency of distributed, needed only by SLURM/PBS clusters

    addrs = psutil.net_if_addrs()
    ipv4 = [a.address for a in addrs.get(name, []) if a.family == socket.AF_INET]
    if ipv4:
        return ipv4[0]
    have = ", ".join(f"{n} ({a.address})" for n, lst in sorted(addrs.items()) for a in lst
                     if a.family == socket.AF_INET)
    raise InputError("cluster", "cluster.interface", f"this machine has no interface '{name}' with an IPv4 address",
                     f"name the interface of the network the compute nodes share with this machine: {have}")


def jobqueue_cluster(cfg, kind, log=print):
    """A dask-jobqueue SLURM or PBS cluster from ``cluster.jobqueue`` (:func:`jobqueue_cluster_and_pools`'s,
    without its pools: e.g. to print its ``job_script()``)."""
    return jobqueue_cluster_and_pools(cfg, kind, log)[0]


def jobqueue_cluster_and_pools(cfg, kind, log=print):
    """A dask-jobqueue SLURM or PBS cluster from ``cluster.jobqueue`` (rest from dask's jobqueue.yaml),
    and its :class:`mmflow.workflow.engine.pools.StagePools` where the jobs are sized per stage (else None).

    The scheduler has to listen on the cluster network (the workers run on other nodes): on
    ``cluster.interface`` (handed to the scheduler only: a worker finds its own address by
    routing to it); its dashboard stays on loopback (reach it with an SSH tunnel) unless
    ``cluster.expose``. What ``cluster.jobqueue`` leaves out is sized from the plan and the
    partition (:func:`mmflow.workflow.engine.batch.job_options`), and a job no node can hold is refused
    here. Nothing is submitted until the cluster is scaled; ``cluster.job_script()`` shows the script.
    """
    import dask_jobqueue  # deferred: dask_jobqueue takes 1-3 s to import (docs/performance.md), SLURM/PBS only

    cls = dask_jobqueue.SLURMCluster if kind == "slurm" else dask_jobqueue.PBSCluster
    pools = plan_pools(cfg, kind, dict(cfg.cluster.jobqueue), log)
    first = next(iter(pools.values())) if pools else None
    opts, sizes = job_options(cfg, kind, log, pool_options(cfg.cluster.jobqueue, first, None) if pools else None)
    refuse_impossible(opts, kind, sizes)
    sched = dict(opts.get("scheduler_options") or {})
    sched.setdefault("dashboard_address", dashboard_bind(cfg.cluster))
    if cfg.cluster.interface:
        interface_address(cfg.cluster.interface)
        sched["interface"] = cfg.cluster.interface
    elif "interface" not in sched and "host" not in sched:
        found = cluster_interface(kind)
        if found:
            sched["interface"] = found[0]
            log(f"cluster.interface unset: the scheduler listens on {found[0]} ({found[1]}), this machine's "
                f"interface on the network of the {kind} nodes (sinfo)")
    opts["scheduler_options"] = sched
    # thread budget: the worker processes of one job share its cores (mmflow.threads.n_threads)
    prologue = list(opts.get("job_script_prologue") or [])
    opts["job_script_prologue"] = prologue + job_prologue(opts.get("processes"))
    cluster = cls(**opts)
    if not pools:
        return cluster, None
    return cluster, StagePools(cluster, pools, dict(cluster._job_kwargs, job_script_prologue=prologue),
                               cfg.cluster.jobqueue.get("walltime"), log)


class LazyClient:
    """A ``distributed.Client`` that starts its cluster on first use.

    A run with nothing to compute (every stage finished, or refused before any work: stale
    settings, a bad input) starts no workers and submits no batch job; the dashboard link is
    printed when the cluster starts. Any attribute of the client (``map``, ``gather``,
    ``scheduler_info``, ...) starts it.
    """

    def __init__(self, start, kind=None):
        self._start = start
        self._client = None
        self._cluster = None
        self.kind = kind  # the cluster's kind, as the dashboard and the report name it
        self._watch = None  # a :class:`mmflow.workflow.engine.batch.JobWatch` for SLURM/PBS workers

    def queue_state(self, log=None):
        """The worker jobs' :class:`mmflow.workflow.engine.batch.QueueState` (lost jobs logged with ``log``
        and replaced); None for a cluster without a batch queue or not started."""
        if self._watch is None or self._client is None:
            return None
        if log is not None:
            self._watch.log = log
        return self._watch.poll(self._client)

    def use_stage(self, stage, log=None):
        """Before ``stage``'s tasks are sent: the worker jobs of its pool where the jobs are sized per
        stage (:class:`mmflow.workflow.engine.pools.StagePools`; the change logged with ``log``);
        nothing for any other cluster. Returns the pool, or None where the jobs are not sized per stage."""
        if self._client is None:
            self._client, self._cluster, self._watch = self._start()
        if self._watch is not None and self._watch.pools is not None:
            return self._watch.pools.use(stage, self._client, self._watch, log)
        return None

    def __getattr__(self, name):  # only for names not found on this object: the client's
        if name.startswith("_"):
            raise AttributeError(name)
        if self._client is None:
            self._client, self._cluster, self._watch = self._start()
        return getattr(self._client, name)

    def close(self):
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()


@contextmanager
def open_cluster(cfg, scheduler=None, kind=None, log=print):
    """Yield a client (a :class:`LazyClient`: the cluster starts when the first task is sent) or
    None for the synchronous scheduler.

    ``scheduler`` (or ``DASK_SCHEDULER_ADDRESS``) joins an existing cluster; ``kind`` overrides
    ``cluster.kind``. Worker memory limits stay on: dask spills, pauses and restarts workers
    that exceed them. A bad ``kind`` or a missing address is refused here, before any work.
    """
    c = cfg.cluster
    kind = kind or ("address" if (scheduler or os.environ.get("DASK_SCHEDULER_ADDRESS")) else c.kind)
    if kind == "synchronous":
        yield None
        return
    addr = scheduler or c.address or os.environ.get("DASK_SCHEDULER_ADDRESS")
    if kind == "address" and not addr:
        raise InputError("cluster", "address", "no scheduler address",
                         "pass --scheduler tcp://host:8786 or set DASK_SCHEDULER_ADDRESS")
    if kind not in ("address", "local", "slurm", "pbs"):
        raise InputError("cluster", "kind", f"unknown cluster kind '{kind}'", "use local, address, slurm or pbs")

    def start():
        from distributed import Client  # deferred: distributed, ~1 s to import; synchronous runs never need it

        from mmflow.workflow.engine.dashboard.page import dashboard_link, serve_page  # deferred: as Client

        serve_page()  # mmflow's page (/mmflow) on the dashboard of a scheduler started here
        cluster = watch = None
        if kind == "address":
            client = Client(addr)
        elif kind == "local":
            from distributed import LocalCluster  # deferred: as Client above

            fork_workers_from_a_preloaded_server()
            cluster = LocalCluster(n_workers=c.n_workers, threads_per_worker=c.threads_per_worker,
                                   memory_limit=memory_limit(c.memory_limit), host=bind_host(c),
                                   dashboard_address=dashboard_bind(c),
                                   env={"MMFLOW_WORKERS_PER_HOST": str(c.n_workers)})  # thread budget per task
            client = Client(cluster)
            if c.expose:
                log(f"cluster.expose: the scheduler ({cluster.scheduler_address}) and dashboard listen on all "
                    "interfaces; anyone who can reach them can run code as you (docs/clusters.md: TLS)")
        else:
            cluster, pools = jobqueue_cluster_and_pools(cfg, kind, log)
            n_jobs = 0 if pools else c.n_workers  # pools: each stage's jobs submitted as it starts
            cluster.scale(jobs=n_jobs)
            client = Client(cluster)
            watch = JobWatch(cluster, kind, n_jobs, cluster._dummy_job.log_directory, log=log, pools=pools)
            log(f"{kind}: " + ("worker jobs submitted per stage" if pools else f"{n_jobs} worker jobs submitted")
                + f"; the scheduler listens on {client.scheduler.address}")
        log(f"dask dashboard: {dashboard_link(cluster, client)}" + (
            f" (mmflow's page: {dashboard_link(cluster, client, 'mmflow')})" if cluster is not None else ""))
        return client, cluster, watch

    client = LazyClient(start, kind)
    try:
        yield client
    finally:
        client.close()
