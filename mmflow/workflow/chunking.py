"""Time chunking of a run: the integrations each time-chunk task covers, and the keys naming them.

The visibility store and every store written per time chunk (``peel.zarr``, ``terrestrial.zarr``)
are chunked along time by :data:`TIME_CHUNK` integrations; a scan of :math:`N` integrations has
:math:`\\lceil N / T \\rceil` chunks, chunk :math:`i` holding rows :math:`[iT, \\min(N, (i+1)T))`.
The stages that work per time chunk (``simulate``, ``ingest``, ``peel``, ``terrestrial``, the models
of ``models``) and the resource plan (:mod:`mmflow.workflow.plan`) share these.
"""
from __future__ import annotations

#: integrations per time-chunk task (and per chunk of the stores written along time)
TIME_CHUNK = 256


def time_keys(n):
    """Task keys ``t00000, t00001, ...`` of the :math:`\\lceil n / T \\rceil` time chunks of ``n`` integrations."""
    return [f"t{i:05d}" for i in range(-(-n // TIME_CHUNK))]


def chunk_rows(key, n):
    """Rows ``(t0, t1)`` of time chunk ``key`` (``"t<i>"``): :math:`[iT, \\min(n, (i+1)T))`."""
    i = int(key[1:])
    return i * TIME_CHUNK, min(n, (i + 1) * TIME_CHUNK)
