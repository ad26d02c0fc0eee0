"""Worker jobs sized per stage from the plan (SLURM/PBS): larger workers only for the stages that need them.

When ``cluster.jobqueue`` gives neither ``cores`` nor ``memory`` (nor does dask's jobqueue.yaml) and
the partition's nodes are known (``sinfo``), a run asks for what ``mmflow plan --cluster slurm`` says:
the cluster plan (:func:`mmflow.workflow.plan.jobs.cluster_plan`) on those nodes gives each stage the
worker its largest task needs, and :func:`mmflow.workflow.plan.jobs.worker_pools` groups the stages by
worker into pools. Before a stage's tasks are sent (:meth:`StagePools.use`):

* a stage of the pool whose jobs are running keeps them (stages of one shape share their jobs; a pool's
  job count is the most any of its stages uses);
* a pool's worker of ``k`` cores has ``k`` of the dask resource :data:`TASK_SLOT`, its core shares, and
  each task of a stage run on pools asks for its pool's worker cores: the plan gives a worker of ``k``
  cores the memory of ``k`` core shares for one task that needs more than ``k - 1`` of them, where dask
  would run ``k`` at once on its ``k`` threads (dask-jobqueue starts ``cores / processes`` threads a
  worker); a worker runs ``k / j`` tasks at once of a stage whose pool's workers have ``j <= k`` cores;
* a stage of a pool of smaller workers keeps the running jobs (its tasks start without a queue wait):
  each of their workers runs as many of its tasks at once as its core shares hold, in the memory of as
  many of the pool's workers; where the pool's own jobs would hold more cores, more jobs of the running
  shape are submitted to make them up;
* a stage of a pool of larger workers first retires the running workers (every task of the stage before has
  finished: stages run one after another), so that no task is ever sent to a worker smaller than the
  plan sized for it, then the cluster's job options become the pool's and it is scaled to the
  pool's jobs; the log says ``stage X: N jobs of C cores / M GB``.

Two stages run channel by channel (``normal`` after ``transfer``: :mod:`mmflow.workflow.engine.channels`)
run in the first one's pool: ``normal``'s tasks go to ``transfer``'s workers, which its plan sizes larger,
rather than switching pools at every channel (its own pool serves ``mmflow normal`` run alone).

The queue handling of :class:`mmflow.workflow.engine.batch.JobWatch` applies to every pool: queued jobs
are waited for, lost jobs are replaced (with the running pool's shape: dask-jobqueue submits
``cluster.new_spec``), workers retire before the pool's walltime.
"""
from __future__ import annotations

from mmflow.errors import InputError
from mmflow.workflow.engine.batch import JOB_START_VAR, jobqueue_default, lifetime_args

#: the job options a pool sets (the rest of ``cluster.jobqueue`` is kept for every pool)
POOL_OPTIONS = ("cores", "memory", "processes", "walltime")
#: the dask worker resource a pool's worker has one of per core (its core shares of memory) and each task of a
#: stage run on pools takes its pool's worker cores of: never more tasks at once than a worker's memory holds
TASK_SLOT = "mmflow_task"


def _per_stage_plan(cfg, kind, opts):
    """``(node, cluster plan)`` where the jobs are sized per stage, else None: ``opts``
    (``cluster.jobqueue``) or dask's jobqueue.yaml give cores or memory, or the partition's nodes are
    unknown (no ``sinfo``: PBS, or SLURM not answering).

    The nodes planned on: ``cluster.n_workers`` where the workflow sets it, else the plan's choice
    (:func:`mmflow.workflow.plan.jobs.choose_nodes`, at most the partition's nodes).
    """
    from mmflow.workflow.plan.jobs import cluster_plan  # deferred: the plan imports every stage
    from mmflow.workflow.plan.nodes import node_size, read_sinfo

    if any(opts.get(k) is not None or jobqueue_default(kind, k) is not None for k in ("cores", "memory")):
        return None
    text = read_sinfo() if kind == "slurm" else None
    if text is None:
        return None
    node = node_size(partition=opts.get("queue") or jobqueue_default(kind, "queue"), sinfo_text=text)
    nodes = cfg.cluster.n_workers if "n_workers" in cfg.cluster.model_fields_set else None
    return node, cluster_plan(cfg, node, nodes)


def split_to_fit(cfg, kind, log=print):
    """The settings that split a task to fit the partition's nodes, ``{key: value}``, where the run's jobs
    are sized per stage and a stage's largest task exceeds a node as the workflow is (else ``{}``).

    They are the cluster plan's (``Cost.split``: ``mmode.baseline_chunk``, ``transfer.m_block``,
    ``transfer.baseline_chunk``, halved until the task fits; :func:`mmflow.workflow.plan.jobs.cluster_plan`).
    ``mmflow run`` applies them as overrides of the workflow before anything starts, which the run's
    ``config.yaml`` records; the same command on the same partition chooses the same again.

    Raises
    ------
    InputError
        No setting makes the task fit a node (the plan's message: the stage, its memory, the limit).
    """
    found = _per_stage_plan(cfg, kind, dict(cfg.cluster.jobqueue))
    if found is None or not found[1]["settings"]:
        return {}
    node, res = found
    log(f"{kind}: {_too_large(node)} (sinfo) as it is: the run splits it with {_given(res)} (the plan's "
        "choice; `mmflow plan --cluster slurm` shows it)")
    return dict(res["settings"])


def _too_large(node):
    return f"a task of this workflow needs more memory than a node of {node.cores} cores and " \
           f"{node.memory_bytes / 1e9:.2f} GB"


def _given(res):
    """The cluster plan's split as overrides, ``'key=value, ...'``."""
    return ", ".join(f"{k}={v}" for k, v in res["settings"].items())


def plan_pools(cfg, kind, opts, log=print):
    """``{stage: pool}`` (:func:`mmflow.workflow.plan.jobs.worker_pools`) of the run, or None where
    the jobs are not sized per stage (:func:`_per_stage_plan`).

    Raises
    ------
    InputError
        A stage's largest task fits a node only with other settings (the plan's split, named: ``mmflow run``
        applies it first, :func:`split_to_fit`), or none.
    """
    from mmflow.workflow.plan.jobs import worker_pools  # deferred: the plan imports every stage

    found = _per_stage_plan(cfg, kind, opts)
    if found is None:
        return None
    node, res = found
    if res["settings"]:
        raise InputError("cluster", "cluster.jobqueue", f"{_too_large(node)} has unless it is split ({_given(res)}; "
                         "`mmflow plan --cluster slurm` shows the plan)", f"rerun with {_given(res)}")
    pools = worker_pools(res)
    log(f"{kind}: worker jobs sized per stage from the plan on {res['nodes']} nodes of {node.cores} cores and "
        f"{node.memory_bytes / 1e9:.2f} GB (sinfo): " + "; ".join(
            f"{', '.join(p['stages'])}: {describe(p)}" for p in _distinct(pools)))
    return pools


def job_prologue(processes):
    """The job script's lines mmflow adds: how many workers share the job's cores (mmflow's thread
    budget) and the job's start time (a worker's ``--lifetime`` counts from it,
    :func:`mmflow.workflow.engine.worker_start.dask_setup`)."""
    return [f"export MMFLOW_WORKERS_PER_HOST={int(processes or 1)}", f"export {JOB_START_VAR}=$(date +%s)"]


def _without_lifetime(args):
    """``worker_extra_args`` without ``--lifetime``/``--lifetime-stagger`` and their values."""
    out, skip = [], False
    for a in args:
        if skip or a in ("--lifetime", "--lifetime-stagger"):
            skip = not skip
            continue
        out.append(a)
    return out


def _user_lifetime(args, walltime):
    """True where ``args``' lifetime is not the one :func:`~mmflow.workflow.engine.batch.lifetime_args`
    makes of ``walltime`` (the workflow set its own)."""
    have = [a for i, a in enumerate(args) if a.startswith("--lifetime") or (i and args[i - 1].startswith("--lifetime"))]
    return bool(have) and have != lifetime_args(walltime)


def _distinct(pools):
    seen = []
    for p in pools.values():
        if not any(p is q for q in seen):
            seen.append(p)
    return seen


def describe(pool):
    """``'N jobs of C cores / M GB'`` (and the workers a job holds where more than one)."""
    from dask.utils import parse_bytes  # deferred: dask takes 0.3-0.8 s to import

    text = f"{pool['count']} jobs of {pool['cores']} cores / {parse_bytes(pool['memory']) / 1e9:.2f} GB"
    return text + (f" ({pool['processes']} workers of {pool['worker_cores']} cores each)"
                   if pool["processes"] > 1 else "")


def pool_options(opts, pool, user_walltime):
    """``opts`` (the job options :func:`mmflow.workflow.engine.batch.job_options` completes) with the
    pool's shape; the workflow's own walltime, where it gives one, wins over the plan's."""
    out = dict(opts, **{k: pool[k] for k in POOL_OPTIONS})
    if user_walltime:
        out["walltime"] = user_walltime
    return out


def with_task_slot(args, shares):
    """``dask worker`` arguments ``args`` with ``shares`` :data:`TASK_SLOT` among the worker's resources
    (added to the workflow's own ``--resources``, where it gives some)."""
    args = list(args)
    if "--resources" not in args:
        return args + ["--resources", f"{TASK_SLOT}={shares}"]
    i = args.index("--resources") + 1
    if TASK_SLOT not in args[i]:
        args[i] = f"{args[i]} {TASK_SLOT}={shares}"
    return args


class StagePools:
    """Switches a dask-jobqueue cluster's jobs to the pool of the stage about to run.

    Parameters
    ----------
    cluster : dask_jobqueue.JobQueueCluster
        Started with no jobs (the first stage's :meth:`use` submits them).
    pools : dict
        ``{stage: pool}`` (:func:`plan_pools`).
    job_kwargs : dict
        The cluster's job options (``cluster._job_kwargs``: the interface, protocol and security
        dask-jobqueue added included), ``job_script_prologue`` without mmflow's lines (:func:`job_prologue`).
    user_walltime : str or None
        ``cluster.jobqueue.walltime`` where given.
    """

    def __init__(self, cluster, pools, job_kwargs, user_walltime, log=print):
        self.cluster, self.pools, self.log = cluster, pools, log
        self.job_kwargs, self.user_walltime = dict(job_kwargs), user_walltime
        args = list(job_kwargs.get("worker_extra_args") or [])
        # the lifetime job_options added from the first pool's walltime is each pool's own; one the workflow set stays
        self.extra_args = None if _user_lifetime(args, job_kwargs.get("walltime")) else _without_lifetime(args)
        self.current = None  # the pool whose jobs are running
        self.serving = None  # the pool whose stage they serve

    def pool_of(self, stage):
        """The stage's pool; a stage the plan does not list (none: every enabled stage with tasks is
        planned) keeps the running pool, else takes the one of the largest workers."""
        if stage in self.pools:
            return self.pools[stage]
        return self.current or max(self.pools.values(), key=lambda p: p["worker_cores"])

    def job_kwargs_of(self, pool):
        """The cluster's job options with ``pool``'s shape, lifetime and mmflow's job lines."""
        kw = pool_options(self.job_kwargs, pool, self.user_walltime)
        if self.extra_args is not None:
            kw["worker_extra_args"] = list(self.extra_args) + lifetime_args(kw["walltime"])
        kw["job_script_prologue"] = list(kw.get("job_script_prologue") or []) + job_prologue(kw["processes"])
        kw["worker_extra_args"] = with_task_slot(kw.get("worker_extra_args") or [], pool["worker_cores"])
        return kw

    def use(self, stage, client, watch=None, log=None):
        """Make the cluster's jobs the stage's pool's (see the module's docstring; the change logged with
        ``log``, default the cluster's); returns the pool."""
        pool = self.pool_of(stage)
        served, self.serving = self.serving, pool
        if pool is self.current or pool is served:
            return pool
        old = set(self.cluster.worker_spec)
        running = self.current
        if old and running is not None and running["worker_cores"] >= pool["worker_cores"]:
            k, j = running["worker_cores"], pool["worker_cores"]
            # as many cores as the pool's own jobs would hold: more jobs of the running shape where it needs more
            want = max(len(old), -(-pool["count"] * pool["cores"] // running["cores"]))
            if want > len(old):
                if watch is not None:
                    watch.n_jobs = want
                self.cluster.scale(jobs=want)
            (log or self.log)(f"stage {stage}: the running jobs kept ({len(old)} of {running['cores']} cores"
                              + (f", {want - len(old)} more submitted" if want > len(old) else "")
                              + f"): a worker runs {k // j} of its tasks at once; for {', '.join(pool['stages'])}")
            return pool
        if old:  # the last stage's workers: none of its tasks is left, and none of this stage's is sent yet
            names = [str(w["name"]) for w in client.scheduler_info().get("workers", {}).values()]
            gone = [n for n in names if any(n == str(o) or n.startswith(f"{o}-") for o in old)]
            if gone:
                client.retire_workers(names=gone, close_workers=True)
            for name in old:
                self.cluster.worker_spec.pop(name, None)
            # new names: a new job under an old one would be taken for the old job, which is then never closed
            self.cluster._i = getattr(self.cluster, "_i", 0) + 1
            if watch is not None:
                watch.retire(old)
        kw = self.job_kwargs_of(pool)
        spec = {"cls": self.cluster.job_cls, "options": kw}
        if kw["processes"] > 1:
            spec["group"] = [f"-{i}" for i in range(kw["processes"])]
        self.cluster._job_kwargs = kw  # what dask-jobqueue's job script and job counts are made from
        self.cluster.new_spec = spec  # what scaling submits, replacements of lost jobs included
        self.current = pool
        if watch is not None:
            watch.n_jobs = pool["count"]
        self.cluster.scale(jobs=pool["count"])
        (log or self.log)(f"stage {stage}: {describe(pool)}" + (" (the running jobs retired)" if old else "")
                 + f", walltime {kw['walltime']}; for {', '.join(pool['stages'])}")
        return pool

