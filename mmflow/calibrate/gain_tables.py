"""Gains of solution intervals at every integration: nearest interval or linear interpolation.

A gain solved over an interval of integrations ``t0 .. t1 - 1`` is its value at the
interval's centre ``c = (t0 + t1 - 1) / 2``. Between two centres ``c_k <= t <= c_{k+1}``
(weight ``x = (t - c_k) / (c_{k+1} - c_k)``) the linear interpolation is, per antenna and
polarisation, in amplitude and in phase separately::

    |g(t)| = (1 - x) |g_k| + x |g_{k+1}|
    arg g(t) = arg g_k + x wrap(arg g_{k+1} - arg g_k),    wrap to (-pi, pi]

after ``g_{k+1}`` is turned by the common phase that best aligns it with ``g_k``
(``exp(-i arg sum_a conj(g_k,a) g_{k+1,a})``: each interval's solution has its own phase
reference, unobservable in ``g_i conj(g_j)``); so a phase that drifts by less than pi between
centres is followed, and amplitudes do not
dip as they would in a linear interpolation of the complex values. Before the first and
after the last centre the nearest solution holds. An integration whose interpolation uses a
flagged solution (weight > 0) is flagged; integrations outside every interval are flagged.
"""
from __future__ import annotations

import numpy as np


def interval_index(rows, intervals):
    """Index of the interval ``[a, b)`` holding each row, -1 outside all (rows (n,), intervals (k, 2))."""
    rows = np.asarray(rows)
    which = np.full(len(rows), -1)
    for k, (a, b) in enumerate(np.asarray(intervals)):
        which[(rows >= a) & (rows < b)] = k
    return which


def gains_at(rows, gains, flags, apply_rows, solve_rows=None, interpolate=False):
    """Gains and flags (len(rows), n_ant, n_pol) of solution intervals at integrations ``rows``.

    Parameters
    ----------
    rows : int array (n,): integration indices
    gains, flags : (k, n_ant, n_pol) solutions per interval (flagged: gain 0)
    apply_rows : (k, 2): the integrations ``[a, b)`` each solution applies to
    solve_rows : (k, 2), optional: the integrations each was solved on (centres; default apply_rows)
    interpolate : bool: linear interpolation between the centres (module docstring), else the
        solution of the interval holding the row

    Returns
    -------
    (gains, flags) per row; rows outside every apply interval are flagged with gain 0.
    """
    rows = np.asarray(rows)
    which = interval_index(rows, apply_rows)
    outside = which < 0
    if not interpolate or len(gains) < 2:
        k = np.maximum(which, 0)
        fl = flags[k] | outside[:, None, None]
        return np.where(fl, 0, gains[k]), fl
    solve = np.asarray(apply_rows if solve_rows is None else solve_rows, float)
    centre = (solve[:, 0] + solve[:, 1] - 1) / 2
    t = np.clip(rows.astype(float), centre[0], centre[-1])
    k = np.clip(np.searchsorted(centre, t, side="right") - 1, 0, len(centre) - 2)
    x = ((t - centre[k]) / (centre[k + 1] - centre[k]))[:, None, None]
    g0, g1 = gains[k], gains[k + 1]
    # each interval has its own phase reference (Stefcal's reference antenna may change): turn g1
    # by the common phase that best aligns it with g0 (unobservable in g_i conj(g_j)) first
    good = ~(flags[k] | flags[k + 1])
    g1 = g1 * np.exp(-1j * np.angle(np.sum(np.where(good, np.conj(g0) * g1, 0), axis=1, keepdims=True)))
    amp = (1 - x) * np.abs(g0) + x * np.abs(g1)
    dphi = np.angle(g1 * np.conj(g0))
    g = amp * np.exp(1j * (np.angle(g0) + x * dphi))
    fl = (flags[k] & (x < 1)) | (flags[k + 1] & (x > 0)) | outside[:, None, None]  # the solutions used
    return np.where(fl, 0, g), fl
