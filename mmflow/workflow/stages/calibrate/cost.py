"""The calibrate stage's cost: a task per solution interval and channel, in two phases that never overlap.

* the read (:func:`mmflow.workflow.engine.blocks.read_block`): the ``vis.zarr`` chunks zarr decodes at once,
  beside the block as read (complex128 + float64);
* the solve: held through it, the interval's data (the block as read and its ripple-corrected copy), the
  current model, the screen rounds' weights and masked data (complex128 and float64 a sample), each
  calibrator's model (complex128, one per feed through an E-field beam, :func:`mmflow.telescope.jones.feed_telescopes`)
  and the code its first task loads; beside them, the larger of Stefcal's rise and a batch of the screen fits.
  Stefcal (:func:`mmflow.calibrate.stefcal.dense_problem`) makes antenna matrices of ``E = L n_pol n_ant^2``
  elements, data and model complex128 and weights float64: its peak is either while the model's matrices are
  made (the data's made, the weights and two baseline-layout copies of the model beside them) or in the
  outlier search (every matrix made, and a block of :func:`mmflow.calibrate.outliers.baseline_residuals`).

The decoded chunks are freed when the read returns, before the solve allocates, so the working set is
the larger phase, not their sum:

.. math:: W = \\max(D + 24\\,S,\\; C + H S + M_{src} + \\max(R_{stefcal}, R_{screen})),

.. math:: R_{stefcal} = \\max(32\\,E + 40\\,S,\\; 40\\,E + 72\\,\\min(L, B / n_{ant}^2)\\,n_{ant}^2),

``S = L n_{bl} n_{pol}`` the interval's samples, ``D`` the decoded chunks, ``C`` the code, ``H`` the bytes a
sample held, ``M_src`` the calibrators' models, ``B`` :data:`~mmflow.calibrate.outliers.RESIDUAL_BLOCK_ELEMENTS`.
Traced on the paper's array (256 antennas, 11 sources, short dipoles, a 30-min interval of 138 integrations):
3.37 GB, the model 3.36; at 64 antennas (the traced test's run) 0.110 GB in a fresh process, the model 0.107.
Many baselines and few integrations (352 antennas over a short track, one integration per solve) make ``D``
(whole chunks of :data:`TIME_CHUNK` integrations) the peak: traced 0.131 GB for the read alone and
0.133 GB for the task in a fresh process, where the sum of both phases planned 0.18 GB.

Each screen round costs ~4 catalogue solves: a gain solve and the screen fits' antenna matrices
(``mmflow bench calibrate``, gains_screened; docs/calibration.md).

Full Stokes costs the same: the gains are solved on the parallel hands, and the cross hands are only read
and corrected where a later stage reads them (measured 1.06x the Stokes-I tasks' time with the paper's
sources at 256 antennas, ``benchmarks/four_correlation_ratio.py``, docs/stokes.md).
"""
from __future__ import annotations

import numpy as np

from mmflow.calibrate.outliers import RESIDUAL_BLOCK_ELEMENTS
from mmflow.io import calibration_stores as cs
from mmflow.telescope.jones import feed_telescopes
from mmflow.workflow.engine.blocks import decode_group_chunks
from mmflow.workflow.engine.chunking import TIME_CHUNK
from mmflow.workflow.plan.work import COMPLEX128_BYTES, CORRECTED_SAMPLE_BYTES, Cost, Work

#: bytes per sample of the block while its read decodes: the complex128 visibilities and float64 weights it
#: returns (the vis read's complex64 and the weights' float32 decoded chunks, half the vis', fit within these)
READ_SAMPLE_BYTES = CORRECTED_SAMPLE_BYTES
#: bytes per sample of the interval as the task holds it: the block read (complex128 + float64), its
#: selected, ripple-corrected copy (:func:`mmflow.calibrate.ripple.apply_ripple`) and the current model (complex128)
HELD_SAMPLE_BYTES = 2 * CORRECTED_SAMPLE_BYTES + COMPLEX128_BYTES
#: bytes per element of Stefcal's antenna matrices (:func:`mmflow.calibrate.stefcal.dense_problem`): the data and
#: the model (complex128) and the weights (float64)
DENSE_ELEMENT_BYTES = 2 * COMPLEX128_BYTES + 8.0
#: bytes per sample beside the data's and the model's matrices while the model's are made: the weights (float64)
#: and the model's two baseline-layout copies (the finite values, then polarisation-major; complex128)
DENSE_BUILD_SAMPLE_BYTES = 8.0 + 2 * COMPLEX128_BYTES
#: bytes per antenna-matrix element of a block of the outlier search's residuals
#: (:func:`mmflow.calibrate.outliers.baseline_residuals`): the model through the gains and the residual
#: (complex128), the residual's and the model's powers and their weighted products (float64)
RESIDUAL_ELEMENT_BYTES = 2 * COMPLEX128_BYTES + 5 * 8.0
#: bytes per sample of the interval the screen rounds add
#: (:func:`mmflow.calibrate.screened_gains.solve_gains_screened`): the weights (float64), the masked data (complex128)
SCREEN_SAMPLE_BYTES = 8.0 + COMPLEX128_BYTES
#: bytes per sample of a batch of the screen fits (:func:`mmflow.calibrate.screened_gains._fit_screens`): the gain
#: products, the unscreened sources' sum and the two arrays of the residual ``v - g rest`` (complex128 each)
SCREEN_BATCH_SAMPLE_BYTES = 4 * COMPLEX128_BYTES
#: complex128 antenna matrices per integration of a batch of the screen fits (the data, weights, each
#: screened source's model, the residual and its screened part)
SCREEN_MATRICES = 6
#: integrations whose screens are fitted together (``solve_gains_screened``'s ``batch``)
SCREEN_BATCH = 16
#: chunks zarr decodes at once (its ``async.concurrency``, 10 by default): an interval of a few integrations
#: reads whole ``vis.zarr`` chunks of ``TIME_CHUNK x mmode.baseline_chunk`` samples (zarr allocates a chunk's
#: full shape, also for a short last time or baseline chunk), which then outweigh its own arrays; at most a
#: group of :func:`mmflow.workflow.engine.blocks.decode_group_chunks` at once; freed when the read returns
ZARR_CONCURRENCY = 10
#: bytes of a decoded visibility (complex64, as ``vis.zarr`` holds it)
DECODED_SAMPLE_BYTES = 8.0
#: what the first gains task of a worker loads besides its arrays: the catalogue's astropy tables and the
#: modules and numba-typed kernels of the solvers (traced: 21 MB in a fresh process, 15 MB after the simulate
#: stage in the same one; a task of a short track at 352 antennas holds ~50 MB of arrays beside it)
CODE_BYTES = 20e6


def solve_sizes(g, cfg):
    """``(calibrators, screen rounds, integrations per solve)``: an interval, or (``solint_s`` null) the
    one track where the sources are highest."""
    cal = cfg.calibrate
    n_src = len(cal.sources) if cal.enabled else 0
    rounds = cal.screen_rounds if cal.enabled and set(cal.screen_sources) & set(cal.sources) else 0
    # at least one integration, as the stage's intervals and track are (`calibrate.stage._intervals`)
    span_s = cal.solint_s if cal.solint_s else 60.0 * cal.track_min
    interval = max(1, int(round(span_s / cfg.observation.integration_s)))
    return n_src, rounds, interval


def stefcal_rise(L, n_samples, n_ant, n_pol):
    """Bytes Stefcal adds to what its caller holds (module docstring's ``R_stefcal``): its antenna matrices of
    ``L`` integrations while the model's are made, or all of them in the outlier search."""
    elements = L * n_pol * n_ant ** 2
    build = (DENSE_ELEMENT_BYTES - 8.0) * elements + DENSE_BUILD_SAMPLE_BYTES * n_samples
    block = min(L, max(1, RESIDUAL_BLOCK_ELEMENTS // n_ant ** 2)) * n_ant ** 2
    return max(build, DENSE_ELEMENT_BYTES * elements + RESIDUAL_ELEMENT_BYTES * block)


def work(g, cfg):
    n_src, rounds, interval = solve_sizes(g, cfg)
    L = min(interval, g.n_time)
    n_int = -(-g.n_time // L) if cfg.calibrate.solint_s else 1  # null: one solve, on the track
    samples = L * g.n_bl * g.n_pol
    chunk = TIME_CHUNK * g.mmode_chunk * g.n_pol * DECODED_SAMPLE_BYTES
    decoded = min(-(-g.n_bl // g.mmode_chunk), ZARR_CONCURRENCY, decode_group_chunks(chunk)) * chunk
    read = decoded + samples * READ_SAMPLE_BYTES
    models = COMPLEX128_BYTES * max(1, n_src) * L * g.n_bl * (g.n_pol if feed_telescopes(g.tel) else 1)
    held = CODE_BYTES + samples * (HELD_SAMPLE_BYTES + (SCREEN_SAMPLE_BYTES if rounds else 0.0)) + models
    rise = stefcal_rise(L, samples, g.n_ant, g.n_pol)
    if rounds:  # a batch of the screen fits: its arrays and antenna matrices (a short interval: its own)
        batch = min(SCREEN_BATCH, L)
        rise = max(rise, batch * SCREEN_BATCH_SAMPLE_BYTES * g.n_bl * g.n_pol
                   + SCREEN_MATRICES * batch * COMPLEX128_BYTES * g.n_pol * g.n_ant ** 2)
    w = max(read, held + rise)  # the decoded chunks are freed before the solve allocates
    spec = cs.gains_store(n_int, g.n_freq, g.n_ant, g.n_pol, g.n_time, np.zeros((n_int, 2), int),
                          np.zeros((n_int, 2), int), {}, n_src=max(1, n_src))
    units = L * g.n_bl * g.n_pol * max(1, n_src) * (1 + 4 * rounds)
    return Work(n_int * g.n_freq, w, units, [spec])


COST = Cost(work, shrink="a shorter calibrate.solint_s")
