"""The calibrate stage's cost: a task per solution interval and channel, holding the interval's data and
each calibrator's model (complex128), and with screened sources the screen rounds' arrays.

Each screen round costs ~4 catalogue solves: a gain solve and the screen fits' antenna matrices
(``mmflow bench calibrate``, gains_screened; docs/calibration.md).
"""
from __future__ import annotations

import numpy as np

from mmflow.io import run_stores as rs
from mmflow.workflow.plan.work import COMPLEX128_BYTES, VIS_SAMPLE_BYTES, Cost, Work

#: bytes per sample a screen round adds: the screened model, the masked data and their weights
SCREEN_SAMPLE_BYTES = 56.0
#: antenna matrices of a batch of the screen fits: six complex128 matrices for 16 integrations
SCREEN_BATCH_MATRICES = 6 * 16


def solve_sizes(g, cfg):
    """``(calibrators, screen rounds, integrations per solve)``: an interval, or (``solint_s`` null) the
    one track where the sources are highest."""
    cal = cfg.calibrate
    n_src = len(cal.sources) if cal.enabled else 0
    rounds = cal.screen_rounds if cal.enabled and set(cal.screen_sources) & set(cal.sources) else 0
    interval = int(round((cal.solint_s if cal.solint_s else 60.0 * cal.track_min) / cfg.observation.integration_s))
    return n_src, rounds, interval


def work(g, cfg):
    n_src, rounds, interval = solve_sizes(g, cfg)
    L = max(1, min(interval or g.n_time, g.n_time))
    n_int = -(-g.n_time // L) if cfg.calibrate.solint_s else 1  # null: one solve, on the track
    w = L * g.n_bl * g.n_pol * (VIS_SAMPLE_BYTES + COMPLEX128_BYTES * max(1, n_src))
    if rounds:  # the screened model, the masked data and weights; a batch's antenna matrices
        w += (
            L * g.n_bl * g.n_pol * SCREEN_SAMPLE_BYTES + SCREEN_BATCH_MATRICES * COMPLEX128_BYTES * g.n_pol * g.n_ant**2
        )
    spec = rs.gains_store(n_int, g.n_freq, g.n_ant, g.n_pol, g.n_time, np.zeros((n_int, 2), int),
                          np.zeros((n_int, 2), int), {}, n_src=max(1, n_src))
    units = L * g.n_bl * g.n_pol * max(1, n_src) * (1 + 4 * rounds)
    return Work(n_int * g.n_freq, w, units, [spec])


COST = Cost(work, shrink="a shorter calibrate.solint_s")
