"""The terrestrial stage's cost: a task per channel and time chunk in each of its two phases (the
template's sum, its removal), reading its channel of the chunk with the corrections before it (with
peeling on, the peel's correction on read is its peak: :func:`mmflow.workflow.plan.work.read_bytes`), then
its weights, the masked data and their product (:data:`SUMS_SAMPLE_BYTES`)."""
from __future__ import annotations

from mmflow.io import calibration_stores as cs
from mmflow.workflow.engine.chunking import TIME_CHUNK
from mmflow.workflow.plan.work import (COMPLEX128_BYTES, CORRECTED_SAMPLE_BYTES, Cost, Work, four_correlation_note,
                                       four_correlations, read_bytes)

#: bytes per sample a task holds beside its block: the weights (float64), the masked data and the weighted
#: data (complex128 each)
SUMS_SAMPLE_BYTES = 8.0 + 2 * COMPLEX128_BYTES
#: a four-correlation task's time over the same task's on the parallel hands: the peel's correction on read
#: and the modelled sources in all four correlations (each source's four correlations through the E-field
#: beam), the cross hands' template fit; measured 2.74 with the paper's sources at 256 antennas
#: (``benchmarks/four_correlation_ratio.py``, docs/stokes.md)
FOUR_CORRELATION_TIME = 2.74


def work(g, cfg):
    n_tchunk = g.n_time_chunks
    four = four_correlations(cfg)  # the cross hands' coefficients too
    spec = cs.terrestrial_store(n_tchunk, g.n_time, g.n_freq, g.n_bl, cfg.terrestrial.components, g.n_ant, g.n_pol,
                                TIME_CHUNK, cross=four)
    T = g.chunk_integrations
    w = max(read_bytes(g, cfg, T, g.n_bl, 1), T * g.n_bl * g.n_pol * (CORRECTED_SAMPLE_BYTES + SUMS_SAMPLE_BYTES))
    return Work(2 * n_tchunk * g.n_freq, w, T * g.n_bl * g.n_pol * (FOUR_CORRELATION_TIME if four else 1.0), [spec])


def notes(g, cfg, peak_gflops):
    return [four_correlation_note(FOUR_CORRELATION_TIME)] if four_correlations(cfg) else []


COST = Cost(work, notes=notes)
