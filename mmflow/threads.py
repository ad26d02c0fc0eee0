"""How many threads a kernel may use: one budget per task, never hard-coded.

Order: the ``MMFLOW_THREADS`` environment variable; inside a dask worker, the cores this
process may use (CPU affinity, capped by a cgroup CPU quota) divided among the worker's
threads and the workers sharing the host (``MMFLOW_WORKERS_PER_HOST``, set by mmflow's own
clusters); otherwise the usable cores.
"""
import os
import sys
from contextlib import contextmanager
from functools import lru_cache

import scipy.linalg  # noqa: F401  -- load scipy's own BLAS first, so the threadpoolctl controller sees it
from threadpoolctl import ThreadpoolController


def usable_cores():
    """Cores this process may run on: its CPU affinity, capped by a cgroup CPU quota."""
    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    quota = _cgroup_cpus()
    return max(1, min(n, int(quota))) if quota else max(1, n)


@lru_cache(maxsize=1)
def _cgroup_cpus():
    """CPUs granted by a cgroup quota (v2 ``cpu.max`` or v1 ``cfs_quota/period``), or None.

    Read once per process: every kernel asks :func:`n_threads`, and the files cost ~0.2 ms a read
    (7,000 reads, 1.4 s, in the calibration demo's calibrate stage)."""
    try:
        text = open("/sys/fs/cgroup/cpu.max").read().split()
        if text[0] != "max":
            return int(text[0]) / int(text[1])
    except (OSError, IndexError, ValueError):
        pass
    try:
        quota = int(open("/sys/fs/cgroup/cpu/cpu.cfs_quota_us").read())
        period = int(open("/sys/fs/cgroup/cpu/cpu.cfs_period_us").read())
        return quota / period if quota > 0 else None
    except (OSError, ValueError):
        return None


def cores_per_thread(worker_threads=1, workers_per_host=1):
    """A kernel's thread budget in a worker of ``worker_threads`` threads, one of ``workers_per_host`` on its
    host: ``MMFLOW_THREADS`` where set, else the usable cores divided among all those threads (at least 1).
    The planner asks it for the workers a run will start (``mmflow.workflow.plan.planner.task_threads``)."""
    env = os.environ.get("MMFLOW_THREADS")
    if env:
        return max(1, int(env))
    return max(1, usable_cores() // (max(1, worker_threads) * max(1, workers_per_host)))


def n_threads():
    """The calling task's thread budget: :func:`cores_per_thread` for the tasks its worker runs at once
    (:func:`concurrent_tasks`) and the workers on its host (``MMFLOW_WORKERS_PER_HOST``)."""
    dist = sys.modules.get("distributed")  # a process outside any dask worker never imports it (~15 MB, ~0.5 s)
    if dist is None or os.environ.get("MMFLOW_THREADS"):
        return cores_per_thread()
    try:
        w = dist.get_worker()
    except (ValueError, AttributeError):  # distributed loaded, but not in a worker (a client, a driver)
        return cores_per_thread()
    return cores_per_thread(concurrent_tasks(w), int(os.environ.get("MMFLOW_WORKERS_PER_HOST", "1")))


def concurrent_tasks(worker):
    """How many tasks like the calling one ``worker`` (a dask worker) runs at once.

    Its threads, unless the task is restricted to a share of a worker resource (SLURM/PBS jobs sized per
    stage: each task of a ``k``-core worker takes all of its ``k`` task slots,
    :mod:`mmflow.workflow.engine.pools`); then ``min over resources r of floor(total_r / share_r)``, so a
    ``k``-core worker's one task runs its kernels on the worker's ``k`` cores, not on one.
    """
    nthreads = max(1, worker.state.nthreads)
    try:
        ts = worker.state.tasks.get(worker.get_current_task())
    except (AttributeError, KeyError, ValueError):  # not in a task's own thread (a kernel's pool thread)
        return nthreads
    shares = getattr(ts, "resource_restrictions", None) or {}
    fits = [int(worker.state.total_resources.get(r, 0) // need) for r, need in shares.items() if need > 0]
    return max(1, min([nthreads, *fits]))


@contextmanager
def single_threaded_blas(active=True):
    """Limit BLAS to one thread while a kernel runs its own ``n_threads()`` workers.

    A kernel that splits its work over a thread pool would otherwise have each pool thread
    start its own BLAS threads (``n_threads()**2`` on ``n_threads()`` cores). Where BLAS
    already runs one thread (every workflow task: :func:`blas_on_one_thread`; dask worker
    processes start that way) nothing is switched, so concurrent tasks of one worker never
    change each other's BLAS settings; elsewhere (a kernel called from a user's own process)
    the limit is process-wide for its duration (threadpoolctl).
    """
    if not active:
        yield
        return
    with blas_on_one_thread():
        yield


@contextmanager
def blas_on_one_thread(for_good=False):
    """BLAS on one thread while a workflow task runs, whatever the process's BLAS threads.

    A task's bits must not depend on where it runs: OpenBLAS's GEMM on two threads rounds most
    elements of a product otherwise than on one (OpenBLAS 0.3.30: 76 % of a float32
    ``(500, 1000) @ (1000, 64)``, 90 % of a complex64 ``(200, 300) @ (300, 1024)``), so a synchronous
    run (the driver's BLAS threads) and a dask worker (one BLAS thread by dask's ``pre-spawn-environ``,
    unless the submitting shell exported ``OPENBLAS_NUM_THREADS``, which a batch job inherits) would
    differ in the last bit, as would two tasks of one worker whose :func:`single_threaded_blas`
    limits restored each other's. Kernels parallelise over their own ``n_threads()`` pools instead.

    ``for_good``: set for the rest of the process (a dask worker, whose tasks run concurrently: a
    limit restored at one task's end would give BLAS its threads back under another task's
    kernel); otherwise restored on exit (a synchronous run in a user's process, one task at a time).
    """
    if blas_threads() <= 1:
        yield
        return
    if for_good:
        _controller().limit(limits=1, user_api="blas")  # applied now; never restored
        yield
        return
    with _controller().limit(limits=1, user_api="blas"):
        yield


def blas_threads():
    """BLAS threads now (the fewest of the loaded libraries'; ~5 us a query: docs/performance.md)."""
    return min((lib.num_threads for lib in _controller().select(user_api="blas").lib_controllers), default=1)


@lru_cache(maxsize=1)
def _controller():
    """One threadpoolctl controller per process: the libraries are scanned once, a limit on a known
    controller is cheap (transfer matrices enter one per few m; costs: docs/performance.md)."""
    return ThreadpoolController()
