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
    dist = sys.modules.get("distributed")  # a process outside any dask worker never imports it (~15 MB, ~0.5 s)
    if dist is None or os.environ.get("MMFLOW_THREADS"):
        return cores_per_thread()
    try:
        w = dist.get_worker()
        return cores_per_thread(w.state.nthreads, int(os.environ.get("MMFLOW_WORKERS_PER_HOST", "1")))
    except (ValueError, AttributeError):  # distributed loaded, but not in a worker (a client, a driver)
        return cores_per_thread()


@contextmanager
def single_threaded_blas(active=True):
    """Limit BLAS to one thread while a kernel runs its own ``n_threads()`` workers.

    A kernel that splits its work over a thread pool would otherwise have each pool thread
    start its own BLAS threads (``n_threads()**2`` on ``n_threads()`` cores). Where BLAS
    already runs one thread (dask worker processes start that way) nothing is switched, so
    concurrent tasks of one worker never change each other's BLAS settings; elsewhere the
    limit is process-wide for its duration (threadpoolctl).
    """
    if not active or _blas_threads() <= 1:
        yield
        return
    with _controller().limit(limits=1, user_api="blas"):
        yield


@lru_cache(maxsize=1)
def _blas_threads():
    """BLAS threads at the process's first use (queried once per process; cost: docs/performance.md)."""
    return min((lib.num_threads for lib in _controller().select(user_api="blas").lib_controllers), default=1)


@lru_cache(maxsize=1)
def _controller():
    """One threadpoolctl controller per process: the libraries are scanned once, a limit on a known
    controller is cheap (transfer matrices enter one per few m; costs: docs/performance.md)."""
    return ThreadpoolController()
