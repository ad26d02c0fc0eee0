"""How many threads a kernel may use: one knob, never hard-coded.

Order: ``MMFLOW_THREADS`` environment variable, then the dask worker's thread count when
running inside a worker (so tasks do not oversubscribe), then ``os.cpu_count()``.
"""
import os


def n_threads():
    env = os.environ.get("MMFLOW_THREADS")
    if env:
        return max(1, int(env))
    try:
        from distributed import get_worker

        w = get_worker()
        return max(1, int(os.cpu_count() or 1) // max(1, w.state.nthreads))
    except (ImportError, ValueError, AttributeError):
        return max(1, int(os.cpu_count() or 1))
