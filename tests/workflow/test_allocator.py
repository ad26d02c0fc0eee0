"""mmflow.allocator: arrays freed and allocated again come from memory the process holds.

dask workers start with ``MALLOC_TRIM_THRESHOLD_=65536``; there every array above 128 kB is a
fresh mmap that page-faults in on first touch. Counted in minor page faults (not time), in a
subprocess started with dask's environment.
"""
import os
import subprocess
import sys

import pytest

from mmflow.allocator import _glibc

PROBE = r"""
import resource, sys
import numpy as np
from mmflow.allocator import keep_freed_memory

def faults(n=40, mb=8):
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        a = np.empty(mb << 17)   # float64: mb MiB
        a[:] = 1.0               # touch every page
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0

faults(2)
before = faults()
assert keep_freed_memory()
after = faults()
print(before, after)
"""


@pytest.mark.skipif(_glibc() is None, reason="mallopt is glibc's")
def test_freed_arrays_are_reused_under_dask_worker_environment():
    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_="65536")
    env.pop("MMFLOW_MALLOC", None)
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    before, after = map(int, out.stdout.split())
    # the worker default: every 8 MiB array faults in again (numpy asks for huge pages, so a few
    # hundred faults per array rather than 2048); once the thresholds are set, the first array's only
    assert before > 40 * 100
    assert after < 0.05 * before


def test_opt_out_leaves_the_allocator_alone(monkeypatch):
    from mmflow import allocator

    monkeypatch.setenv("MMFLOW_MALLOC", "default")
    allocator.keep_freed_memory.cache_clear()
    try:
        assert allocator.keep_freed_memory() is False
    finally:
        allocator.keep_freed_memory.cache_clear()


RELEASE = r"""
import numpy as np
from mmflow.allocator import keep_freed_memory, release_freed_memory
from mmflow.workflow.engine.resources import current_rss_bytes

assert keep_freed_memory()
arrays = [np.ones((20 << 20) // 8) for _ in range(60)]   # 1.2 GB of 20 MiB arrays: heap, not mmap
kept = arrays[::10]                                       # every tenth stays: the freed ones are holes
del arrays
held = current_rss_bytes()
assert release_freed_memory()
print(held, current_rss_bytes(), sum(a.nbytes for a in kept))
"""


@pytest.mark.skipif(_glibc() is None, reason="malloc_trim is glibc's")
def test_freed_memory_inside_the_heap_is_given_back():
    """Arrays below the mmap threshold freed among arrays still held stay resident (no trim threshold
    returns holes inside the heap: a paper-scale worker began CLEAN with 6 GB so held); malloc_trim(0)
    gives them back, and what is still held stays."""
    out = subprocess.run([sys.executable, "-c", RELEASE], capture_output=True, text=True, check=True)
    held, after, kept = map(int, out.stdout.split())
    assert held > 1.1e9  # the freed arrays were still resident
    assert after < held - 0.9e9 and after > kept  # ~1 GB given back; the six arrays held are not
