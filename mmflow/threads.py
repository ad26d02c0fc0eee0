"""How many threads a kernel may use: one knob, never hard-coded.

Order: ``MMFLOW_THREADS`` environment variable, then the dask worker's thread count when
running inside a worker (so tasks do not oversubscribe), then ``os.cpu_count()``.
"""
import os
from contextlib import contextmanager
from functools import lru_cache


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


@contextmanager
def single_threaded_blas(active=True):
    """Limit BLAS to one thread while a kernel runs its own ``n_threads()`` workers.

    A kernel that splits its work over a thread pool would otherwise have each pool thread
    start its own BLAS threads (``n_threads()**2`` on ``n_threads()`` cores). The limit is
    process-wide for its duration (threadpoolctl); dask workers already run BLAS
    single-threaded, so inside a worker this changes nothing.
    """
    if not active:
        yield
        return
    with _controller().limit(limits=1, user_api="blas"):
        yield


@lru_cache(maxsize=1)
def _controller():
    """One threadpoolctl controller per process: scanning the loaded libraries costs ~0.3 ms,
    a limit on a known controller ~15 us (transfer matrices enter one per few m)."""
    import scipy.linalg  # noqa: F401  -- load scipy's own BLAS first, so the controller sees it
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()
