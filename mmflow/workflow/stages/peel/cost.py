"""The peel stage's cost: a task per time chunk and channel holding its corrected block (complex128 +
float64), the sources' models (complex64, one for both hands), the peeled residual it returns
(complex128, :func:`mmflow.calibrate.peel.peel`'s ``residual``) and a batch's antenna matrices (data,
weights, residual and the models: 16 integrations x hands; the solve runs in single precision)."""
from __future__ import annotations

from mmflow.io import run_stores as rs
from mmflow.workflow.engine.chunking import TIME_CHUNK
from mmflow.workflow.plan.work import CORRECTED_SAMPLE_BYTES, Cost, Work

#: bytes per sample of a source's model: complex64, one for both hands
MODEL_SAMPLE_BYTES = 8.0
#: bytes per sample of the peeled residual (complex128: the solve's output, written back per batch)
RESIDUAL_SAMPLE_BYTES = 16.0
#: integrations of a batch of antenna matrices
BATCH_INTEGRATIONS = 16
#: bytes of an antenna-matrix element (complex64: the peel solves in single precision)
MATRIX_ELEMENT_BYTES = 8.0


def n_sources(cfg):
    """Sources the peel removes or subtracts (at least one for the plan)."""
    return max(1, len(cfg.peel.sources) + len(cfg.peel.model_sources) if cfg.peel.enabled else 0)


def work(g, cfg):
    n_src = n_sources(cfg)
    T = g.chunk_integrations
    w = (T * g.n_bl * ((CORRECTED_SAMPLE_BYTES + RESIDUAL_SAMPLE_BYTES) * g.n_pol + MODEL_SAMPLE_BYTES * n_src)
         + (n_src + 3) * BATCH_INTEGRATIONS * g.n_pol * g.n_ant ** 2 * MATRIX_ELEMENT_BYTES)
    spec = rs.peel_store(g.n_time, g.n_freq, n_src, g.n_ant, g.n_pol, TIME_CHUNK, {})
    return Work(g.n_time_chunks * g.n_freq, w, T * g.n_bl * g.n_pol * n_src, [spec])


COST = Cost(work, shrink="fewer peel.sources / peel.model_sources")
