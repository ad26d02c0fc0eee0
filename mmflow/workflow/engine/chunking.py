"""Time chunking of a run: the integrations each time-chunk task covers, and the keys naming them.

The visibility store and every store written per time chunk (``peel.zarr``, ``terrestrial.zarr``)
are chunked along time by :data:`TIME_CHUNK` integrations; a scan of :math:`N` integrations has
:math:`\\lceil N / T \\rceil` chunks, chunk :math:`i` holding rows :math:`[iT, \\min(N, (i+1)T))`.
The stages that work per time chunk (``simulate``, ``ingest``, ``peel``, ``terrestrial``, the models
of ``models``) and the resource plan (:mod:`mmflow.workflow.plan.planner`) share these.
"""
from __future__ import annotations

from mmflow.workflow.engine.task_key import TaskKey

#: integrations per time-chunk task (and per chunk of the stores written along time)
TIME_CHUNK = 256


def time_keys(n, **fields):
    """Task keys of the :math:`\\lceil n / T \\rceil` time chunks of ``n`` integrations.

    Parameters
    ----------
    n : int
        Integrations in the scan.
    **fields
        Other fields of every key (``freq``, ``phase``): ``time_keys(n, freq=1)`` gives
        ``f1_t00000, f1_t00001, ...``.

    Returns
    -------
    list of TaskKey
        ``TaskKey(time=i, **fields)`` for :math:`i = 0 \\ldots \\lceil n / T \\rceil - 1`.
    """
    return [TaskKey(time=i, **fields) for i in range(-(-n // TIME_CHUNK))]


def chunk_rows(key, n):
    """Rows ``(t0, t1)`` of the time chunk of ``key`` (a :class:`TaskKey` with ``time = i``):
    :math:`[iT, \\min(n, (i+1)T))`."""
    i = key.time
    return i * TIME_CHUNK, min(n, (i + 1) * TIME_CHUNK)
