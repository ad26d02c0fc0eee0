"""What this machine offers, measured: its GEMM peak and a description, for benchmarks and the planner.

A rate means little without the peak of the same machine at the same moment (a shared VM's BLAS
peak swings ~2x): every benchmark reports ``gemm_gflops`` beside its own figures, and
``mmflow plan`` scales its time estimates by it.
"""
from __future__ import annotations

import os
import platform
import time

import numpy as np

from mmflow.threads import n_threads


def best_time(fn, reps=3):
    """The shortest wall time (s) of ``reps`` calls of ``fn()``."""
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def gemm_gflops(dtype, n=1536):
    """GEMM rate (GFLOP/s, ``2 n^3`` flops) of an ``n x n`` product in ``dtype``, best of three."""
    a = np.random.default_rng(0).random((n, n)).astype(dtype)
    b = np.random.default_rng(1).random((n, n)).astype(dtype)
    a @ b
    return 2.0 * n**3 / best_time(lambda: a @ b) / 1e9


def machine():
    """Python and numpy versions, CPUs and the threads a task may use."""
    return {"python": platform.python_version(), "cpus": os.cpu_count(), "threads": n_threads(),
            "numpy": np.__version__}
