"""The simulate stage's cost: per time chunk every channel's visibilities of the sky's points, and with
an interpolated diffuse sky first its direct sums at the sampled sidereal angles.

Memory of a time-chunk task: the chunk's ``vis.zarr`` block and, one channel at a time, a corrupted
simulation's :data:`TEMPORARIES` complex128 ``(time, baseline, pol)`` arrays (drift scans, corruptions,
noise; measured 2.8 GB at 256 antennas, docs/planning.md), or an uncorrupted one's drift scan
(:data:`DRIFT_SCAN_BYTES`) and, with ``sky.noise``, the radiometer noise's arrays
(:data:`NOISE_SAMPLE_BYTES`): 112 B a sample traced at 352 antennas against the 172 B that ten
temporaries and the block counted.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from mmflow.io import calibration_stores as cs
from mmflow.simulate.drift_modes import n_samples
from mmflow.conventions import is_full_stokes
from mmflow.simulate.scene import diffuse_columns, diffuse_quad_lmax
from mmflow.simulate.visibilities import gauss_legendre_shape
from mmflow.workflow.engine.geometry import DIFFUSE_SAMPLE_BLOCK, interpolates_diffuse
from mmflow.workflow.plan.work import COMPLEX128_BYTES, Cost, Work, four_correlation_note, vis_spec

#: complex128 (time, baseline, pol) temporaries of one channel of a corrupted simulation (drift scans,
#: corruptions, noise)
TEMPORARIES = 10
#: bytes per sample of an uncorrupted channel's drift scan (:func:`mmflow.simulate.visibilities.simulate_drift_scan`
#: returns complex128)
DRIFT_SCAN_BYTES = COMPLEX128_BYTES
#: bytes per sample of the radiometer noise (:func:`mmflow.simulate.visibilities.thermal_noise`) at its peak:
#: the two ends' autocorrelations, sigma and the two normal draws (float64 each), the complex noise, the
#: autocorrelations' real noise and the selection between them (complex128 each)
NOISE_SAMPLE_BYTES = 5 * 8.0 + 3 * COMPLEX128_BYTES
#: bytes per sampled angle, baseline and feed column of the diffuse sky's samples and their modes
DIFFUSE_SAMPLE_BYTES = 2 * COMPLEX128_BYTES
#: the share of the SGEMM peak the diffuse sky's direct sums reach (the rank-k product over the antennas and
#: the phasors' sines and cosines), measured at full scale: 138 sums of 1.58M points above the horizon at
#: 256 antennas, 889 s of task time on the 2 workers of a 193 GFLOP/s VM (docs/performance.md)
DIFFUSE_SUM_FRACTION = 0.67
#: a full-Stokes time chunk's task time over the same task's with the sky through the power beams: the four
#: correlations of every point per integration (:func:`mmflow.simulate.polarised.simulate_polarised_drift_scan`,
#: the ``2 n_ant`` feed matrix) and their corruptions; measured 1.74 with the paper's 11 sources at 256
#: antennas (``benchmarks/four_correlation_ratio.py``, docs/stokes.md)
FOUR_CORRELATION_TIME = 1.74
#: complex128 (time, baseline) arrays per cross hand (xy, yx) a full-Stokes channel holds beyond the parallel
#: hands' :data:`TEMPORARIES`: measured 0.68 GB more than the same task through the power beams at 256
#: antennas (4.07 against 3.39 GB, a time chunk: 2.5 a cross hand; ``benchmarks/four_correlation_ratio.py``'s
#: runs, docs/stokes.md)
CROSS_TEMPORARIES = 3


class SkySizes(NamedTuple):
    """What the simulator sums: points per integration, the diffuse grid, its sampled angles, feed columns."""

    points: int  # sources, and the diffuse grid when it is not interpolated
    diffuse_points: int  # the diffuse sky's quadrature grid
    diffuse_samples: int  # sidereal angles of an interpolated diffuse sky (0: none)
    feed_columns: int  # simulated through each feed's power beam (2) or one beam (1); 4 correlations (full Stokes)
    full_stokes: bool  # the four correlations through the E-field beam


def sky_sizes(g, cfg):
    """The :class:`SkySizes` of a simulation: the diffuse sky's grid as the simulator builds it at the
    highest channel (:func:`mmflow.simulate.scene.diffuse_quad_lmax`,
    :func:`mmflow.simulate.visibilities.gauss_legendre_shape`)."""
    s = cfg.sky
    n_diffuse = 0
    if s.diffuse:
        q = diffuse_quad_lmax(g.tel, float(np.max(g.freqs_hz)), s.diffuse_lmax, s.quad_oversample)
        ntheta, nphi = gauss_legendre_shape(q)
        n_diffuse = ntheta * nphi
    interpolated = interpolates_diffuse(cfg)
    full = is_full_stokes(cfg.imaging.stokes)
    return SkySizes(len(s.sources) + (0 if interpolated else n_diffuse), n_diffuse,
                    n_samples(s.diffuse_lmax) if interpolated else 0,
                    diffuse_columns(g.tel, cfg.corrupt.enabled, full), full)


def work(g, cfg):
    sky = sky_sizes(g, cfg)
    T = g.chunk_integrations
    units = T * g.n_bl * g.n_freq * sky.points * (FOUR_CORRELATION_TIME if sky.full_stokes else 1.0)
    w = g.vis_task_bytes
    if cfg.corrupt.enabled or sky.full_stokes:
        w += T * g.n_bl * (g.n_pol * TEMPORARIES + (2 * CROSS_TEMPORARIES if sky.full_stokes else 0)) * COMPLEX128_BYTES
    else:  # scalar and clean: one channel's drift scan and its noise (the chunk's channels: the vis block)
        w += T * g.n_bl * g.n_pol * (DRIFT_SCAN_BYTES + (NOISE_SAMPLE_BYTES if cfg.sky.noise else 0.0))
    if not sky.diffuse_samples:
        return Work(g.n_time_chunks, w, units, [vis_spec(g)])
    # an interpolated diffuse sky: first its direct sums at the sampled angles (DIFFUSE_SAMPLE_BLOCK a task:
    # their time is diffuse_sum_seconds'), then per time chunk its samples, their modes and their evaluation
    # at the chunk's integrations (the units: the time chunks')
    n_d = g.n_freq * -(-sky.diffuse_samples // DIFFUSE_SAMPLE_BLOCK)
    w += (sky.diffuse_samples * g.n_bl * sky.feed_columns * DIFFUSE_SAMPLE_BYTES
          + T * g.n_bl * sky.feed_columns * COMPLEX128_BYTES)
    spec = cs.diffuse_store(g.n_freq, sky.diffuse_samples, g.n_bl, sky.feed_columns, DIFFUSE_SAMPLE_BLOCK)
    return Work(g.n_time_chunks + n_d, w, units, [vis_spec(g), spec])


def diffuse_sum_seconds(g, cfg, peak_gflops):
    """Wall seconds of an interpolated diffuse sky's direct sums on the whole machine: per channel and
    sampled angle ``(2 n_ant)^2 x n_up`` flops (``n_up``, half the quadrature grid, above the horizon), per
    feed column, at :data:`DIFFUSE_SUM_FRACTION` of the SGEMM peak ``peak_gflops``; a full-Stokes
    simulation's four correlations are one complex64 Hermitian rank-``2 n_up`` update of the ``(2 n_ant)^2``
    correlation matrix per angle (:func:`mmflow.simulate.polarised.simulate_polarised_drift_scan`'s
    ``herk``): ``4 (2 n_ant)^2 2 n_up`` flops (assumed at the same share of the peak)."""
    sky = sky_sizes(g, cfg)
    per_sample = (4.0 * (2.0 * g.n_ant) ** 2 * sky.diffuse_points if sky.full_stokes
                  else sky.feed_columns * (2.0 * g.n_ant) ** 2 * sky.diffuse_points / 2)
    flops = g.n_freq * sky.diffuse_samples * per_sample
    return flops / (DIFFUSE_SUM_FRACTION * peak_gflops * 1e9)


def seconds(g, cfg, per_task, workers, peak_gflops):
    """The time chunks by the fitted constants, an interpolated diffuse sky's sums by their flops."""
    chunks = per_task * math.ceil(g.n_time_chunks / max(workers, 1))
    return chunks + (diffuse_sum_seconds(g, cfg, peak_gflops) if sky_sizes(g, cfg).diffuse_samples else 0.0)


def notes(g, cfg, peak_gflops):
    sky = sky_sizes(g, cfg)
    out = [four_correlation_note(FOUR_CORRELATION_TIME)] if sky.full_stokes else []
    if not sky.diffuse_samples:
        return out
    sums = diffuse_sum_seconds(g, cfg, peak_gflops)
    return [f"the diffuse sky: {g.n_freq * sky.diffuse_samples} direct sums, ~{sums / 60:.0f} min"] + out


COST = Cost(work, seconds=seconds, notes=notes)
