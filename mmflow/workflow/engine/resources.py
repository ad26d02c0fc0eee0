"""What a stage costs a process: its peak resident memory, measured per task and per stage.

Linux keeps a high-water mark of each process's resident set (``VmHWM`` in
``/proc/self/status``) and resets it to the current resident set when ``5`` is written to
``/proc/self/clear_refs`` (Linux >= 4.0). A task resets it when it starts and reads it when
it ends, so ``peak_rss`` of a task is the most its worker process held while the task ran
(with one thread per worker, the default, that is the task's own peak plus the worker's
baseline). The driver does the same around each stage.

Where the counter cannot be reset (another OS, a locked-down ``/proc``), the reading falls back
to ``ru_maxrss``, the process's lifetime peak, and :func:`reset_peak_rss` returns False: the
readings are then upper bounds (the runner does not mark them; on Linux >= 4.0 they are exact).
"""
from __future__ import annotations

import resource
import sys
import threading
import tracemalloc

_STATUS = "/proc/self/status"
_CLEAR = "/proc/self/clear_refs"


def _status_kib(field):
    try:
        with open(_STATUS) as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def reset_peak_rss():
    """Reset this process's resident-set high-water mark to its current resident set.

    Returns
    -------
    bool
        True if the mark was reset (later :func:`peak_rss_bytes` readings cover only what
        followed), False where the OS does not allow it.
    """
    try:
        with open(_CLEAR, "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def peak_rss_bytes():
    """This process's peak resident memory in bytes since the last :func:`reset_peak_rss`
    (``VmHWM``), or its lifetime peak (``ru_maxrss``) where ``/proc`` has no ``VmHWM``."""
    kib = _status_kib("VmHWM")
    if kib is not None:
        return kib * 1024
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak if sys.platform == "darwin" else peak * 1024  # bytes on macOS, KiB on Linux


class TasksAtOnce:
    """The most tasks this process ran at once while one task ran, itself included (``with TasksAtOnce() as
    n: ...; n.most``).

    The resident set and ``tracemalloc``'s traced memory are the process's: a worker of several threads that
    runs two tasks at once reads their allocations as one peak, which is not one task's (``mmflow bench
    cluster`` compares a task's traced peak with the plan's only where it ran alone). Every task entering
    raises the count of the tasks already running (a lock: the worker's threads)."""

    _lock = threading.Lock()
    _running = []

    def __enter__(self):
        with self._lock:
            self._running.append(self)
            self.most = 0
            for task in self._running:
                task.most = max(task.most, len(self._running))
        return self

    def __exit__(self, *exc):
        with self._lock:
            self._running.remove(self)
        return False


def reset_traced_peak():
    """Start a task's reading of the memory Python and numpy allocate (``tracemalloc``, only when a
    caller has started tracing it, e.g. a test): returns the bytes traced now, or None when not tracing.

    Unlike the resident set, the traced peak does not depend on what the allocator kept from earlier
    tasks or on one-off caches outside numpy: it is the task's own arrays (numpy registers its data
    buffers with ``tracemalloc``; memory that compiled libraries allocate themselves is not traced).
    """
    if not tracemalloc.is_tracing():
        return None
    tracemalloc.reset_peak()
    return tracemalloc.get_traced_memory()[0]


def traced_peak_bytes(start):
    """The traced peak since :func:`reset_traced_peak` returned ``start``, above it (None if not tracing)."""
    if start is None or not tracemalloc.is_tracing():
        return None
    return tracemalloc.get_traced_memory()[1] - start


def dask_worker():
    """``(name, memory limit in bytes or None)`` of the dask worker running this task (what its cluster
    gave it), or None outside a dask worker."""
    dist = sys.modules.get("distributed")  # a task outside any dask worker never imports it
    if dist is None:
        return None
    try:
        worker = dist.get_worker()
    except ValueError:
        return None
    return str(worker.name), worker.memory_manager.memory_limit or None


def current_rss_bytes():
    """This process's resident memory now (``VmRSS``), or None where ``/proc`` has none."""
    kib = _status_kib("VmRSS")
    return None if kib is None else kib * 1024


def gb(n_bytes):
    """Bytes as GB (1e9), rounded to the MB, for summaries."""
    return None if n_bytes is None else round(n_bytes / 1e9, 3)
