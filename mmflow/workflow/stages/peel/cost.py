"""The peel stage's cost: a task per time chunk and channel holding its corrected block (complex128 +
float64), the sources' models (complex64, one for both hands), the peeled residual it returns
(complex128, :func:`mmflow.calibrate.peel.peel`'s ``residual``), the solve's float64 copy of the weights
and a batch's antenna matrices (data, weights, two copies of the residual, the normal matrix and the
models: 16 integrations x hands; the solve runs in single precision). A
four-correlation peel (full Stokes through an E-field beam) also holds the block's cross hands, each
source's four correlations, and the cross hands' fit (:func:`mmflow.calibrate.cross_hands.fit_cross`:
the templates and the stacked design matrix with its weighted copy, complex128, a batch at a time)."""
from __future__ import annotations

from mmflow.io import calibration_stores as cs
from mmflow.workflow.engine.chunking import TIME_CHUNK
from mmflow.workflow.plan.work import CORRECTED_SAMPLE_BYTES, Cost, Work, four_correlation_note, four_correlations

#: bytes per sample of a source's model: complex64, one for both hands
MODEL_SAMPLE_BYTES = 8.0
#: bytes per sample of the peeled residual (complex128: the solve's output, written back per batch)
RESIDUAL_SAMPLE_BYTES = 16.0
#: integrations of a batch of antenna matrices
BATCH_INTEGRATIONS = 16
#: bytes of an antenna-matrix element (complex64: the peel solves in single precision)
MATRIX_ELEMENT_BYTES = 8.0
#: bytes per element of a batch's antenna matrices besides the sources' models
#: (:func:`mmflow.calibrate.peel.peel`, :func:`~mmflow.calibrate.peel.peel_dense`): the data and two copies of
#: the residual (complex64), the normal matrix's ``W |M|^2`` (float64) and the weights (float32)
BATCH_MATRIX_BYTES = 3 * MATRIX_ELEMENT_BYTES + 8.0 + 4.0
#: bytes per sample of the weights as the solve holds them (float64, broadcast to the data's shape)
WEIGHT_COPY_BYTES = 8.0
#: bytes per cross-hand sample and source of the cross hands' fit: templates, design matrix and its weighted
#: copy (complex128 each)
CROSS_FIT_SAMPLE_BYTES = 48.0
#: a four-correlation task's time over the same task's on the parallel hands: each source's four correlations
#: through the E-field beam (:func:`mmflow.calibrate.coherency.source_correlations`), its cross-hand templates
#: and the cross hands' fit (one GEMM per integration, ``n_src^2`` per sample: the ratio grows with the
#: sources); measured 3.08 with the paper's 11 sources at 256 antennas (``benchmarks/four_correlation_ratio.py``,
#: docs/stokes.md)
FOUR_CORRELATION_TIME = 3.08


def n_sources(cfg):
    """Sources the peel removes or subtracts (at least one for the plan)."""
    return max(1, len(cfg.peel.sources) + len(cfg.peel.model_sources) if cfg.peel.enabled else 0)


def work(g, cfg):
    n_src = n_sources(cfg)
    T = g.chunk_integrations
    four = four_correlations(cfg)
    cross, n_corr = (2, 4) if four else (0, 1)
    w = (T * g.n_bl * ((CORRECTED_SAMPLE_BYTES + RESIDUAL_SAMPLE_BYTES + WEIGHT_COPY_BYTES) * g.n_pol
                       + CORRECTED_SAMPLE_BYTES * cross + MODEL_SAMPLE_BYTES * n_corr * n_src)
         + (n_src * MATRIX_ELEMENT_BYTES + BATCH_MATRIX_BYTES) * BATCH_INTEGRATIONS * g.n_pol * g.n_ant ** 2
         + BATCH_INTEGRATIONS * g.n_bl * cross * n_src * CROSS_FIT_SAMPLE_BYTES)  # the cross fit, a batch at a time
    spec = cs.peel_store(g.n_time, g.n_freq, n_src, g.n_ant, g.n_pol, TIME_CHUNK, {}, cross=four)
    units = T * g.n_bl * g.n_pol * n_src * (FOUR_CORRELATION_TIME if four else 1.0)
    return Work(g.n_time_chunks * g.n_freq, w, units, [spec])


def notes(g, cfg, peak_gflops):
    return [four_correlation_note(FOUR_CORRELATION_TIME)] if four_correlations(cfg) else []


COST = Cost(work, shrink="fewer peel.sources / peel.model_sources", notes=notes)
