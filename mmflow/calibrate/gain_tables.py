"""Gains of solution intervals at every integration: nearest interval, linear interpolation, or a
weighted local polynomial fit in time (:func:`smooth_gains_at`, the default recipe's).

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

Interpolation follows every interval's solution, including the part of it that the unmodelled sky
moved (a gain error correlated with the unmodelled sources at that hour, which then takes a share
of their flux out of the map: 8-17 % on the independent day of ``docs/calibration.md``).
:func:`smooth_gains_at` instead fits a low-order polynomial per integration to the solutions of the
intervals within a kernel of a few of them, each weighted by how well the model explained its data
(:func:`interval_weights`): a drift slower than the kernel is followed, the unmodelled sky's part,
uncorrelated between intervals hours apart, is averaged down.
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


def interval_weights(unexplained, max_unexplained):
    """Weights of interval solutions (same shape as ``unexplained``, intervals first): ``1 / u`` where
    the fraction ``u`` of the data's power that the calibrated model leaves is at most ``max_unexplained``
    or is the smallest of its column (the best interval is always used), else 0 (NaN: no data, 0).

    A gain solution's error from the unmodelled sky and the noise has a variance ~ ``u`` (their power over
    the model's, which then is most of the data's), so ``1 / u`` is its inverse variance up to a constant."""
    u = np.asarray(unexplained, float)
    finite = np.isfinite(u)
    best = np.nanmin(np.where(finite, u, np.inf), axis=0, keepdims=True)
    use = finite & ((u <= max_unexplained) | (u <= best))
    return np.where(use, 1.0 / np.maximum(np.where(finite, u, 1.0), 1e-12), 0.0)


def aligned_phases(gains, weights):
    """Per interval, antenna and polarisation, ``arg g`` on one phase reference (k, n_ant, n_pol).

    Each interval's solution has its own phase reference (unobservable in ``g_i conj(g_j)``). The
    interval with the largest total weight ``r`` is the reference; every interval ``k`` is turned
    by ``exp(-i phi_k)``, ``phi_k = arg sum_a w_ka conj(g_ra) g_ka`` (per polarisation), and its
    phases are taken relative to the reference's: ``arg g_ka = arg g_ra + arg(g_ka conj(g_ra)
    exp(-i phi_k))``, which follows a drift of less than pi from the reference."""
    r = int(np.argmax(weights.sum((1, 2))))
    ref = gains[r]
    phi = np.angle(np.sum(weights * np.conj(ref)[None] * gains, axis=1, keepdims=True))
    return np.angle(ref)[None] + np.angle(gains * np.conj(ref)[None] * np.exp(-1j * phi))


def smooth_gains_at(rows, gains, flags, solve_rows, weights, scale, degree=1):
    """Gains (len(rows), n_ant, n_pol) from interval solutions by a weighted local polynomial fit in time.

    Per antenna and polarisation, ``y_k = log |g_k|`` and the aligned phase (:func:`aligned_phases`) of
    the interval solutions at their centres ``c_k`` are fitted at each row ``t`` by a polynomial of
    ``degree`` in ``x_k = (c_k - t) / scale``, minimising::

        sum_k w_k exp(-x_k^2 / 2) (y_k - sum_j a_j x_k^j)^2,    y(t) = a_0

    ``w_k`` the interval's weight (``weights`` (k,) or (k, n_ant, n_pol); 0 where flagged): how far its
    solution is to be trusted (:func:`interval_weights`). A drift slower than ``scale`` is followed
    (a local quadratic's bias on a sinusoid of period ``P`` is ``1 - (1 + z / 2) exp(-z / 2)``,
    ``z = (2 pi scale / P)^2``: 2 % for ``scale`` = 1.5 h and ``P`` = 10 h); the part of each solution
    that the unmodelled sky moved (uncorrelated between intervals hours apart) is averaged down. Rows
    beyond the first and last interval of weight > 0 take the fit there (no extrapolation); across a
    long run of intervals of weight 0 the kernel is renormalised to the nearest used ones, whose fit
    holds. A row whose antenna has no weight at all is flagged (gain 0).

    Parameters
    ----------
    rows : int array (n,); gains, flags : (k, n_ant, n_pol); solve_rows : (k, 2)
    weights : (k,) or (k, n_ant, n_pol) >= 0; scale : float, the kernel's sigma (integrations)
    degree : int, 0 (a weighted mean), 1 (local linear: no bias on a linear drift), 2, ...

    Returns
    -------
    (gains, flags) per row
    """
    rows = np.asarray(rows, float)
    solve = np.asarray(solve_rows, float)
    centre = (solve[:, 0] + solve[:, 1] - 1) / 2
    w = np.asarray(weights, float)
    w = np.where(flags, 0.0, np.broadcast_to(w[:, None, None] if w.ndim == 1 else w, gains.shape))
    amp = np.log(np.where(flags, 1.0, np.abs(np.where(gains == 0, 1.0, gains))))
    phase = aligned_phases(np.where(flags, 0, gains), w)
    used = (w > 0).any((1, 2))
    if used.any():  # beyond the first and last used centre the fit there holds (no extrapolation)
        rows = np.clip(rows, centre[used].min(), centre[used].max())
    d = centre[None, :] - rows[:, None]  # (n, k)
    logk = -0.5 * (d / scale) ** 2
    if used.any():  # each row's kernel over its nearest used interval: far from all, the nearest ones hold
        logk = logk - logk[:, used].max(1, keepdims=True)
    kern = np.exp(logk)  # (n, k); times w (k, a, p): the fit's weights
    shape = (len(rows),) + gains.shape[1:]
    wf = w.reshape(len(gains), -1)  # (k, a * p)
    s0 = (kern @ wf).reshape(shape)
    fl = s0 <= 1e-12 * max(float(w.max()), 1e-300)
    x = (d / scale)[..., None] ** np.arange(degree + 1)  # (n, k, j): the polynomial in (c_k - t) / scale
    moments = kern[..., None, None] * x[..., :, None] * x[..., None, :]  # (n, k, i, j)
    a = np.swapaxes(np.swapaxes(moments.reshape(len(rows), len(gains), -1), 1, 2) @ wf, 1, 2)  # (n, a * p, i j)
    a = a.reshape(shape + (degree + 1, degree + 1))
    a += 1e-9 * s0[..., None, None] * np.diag(np.r_[0.0, np.ones(degree)])  # few intervals near: a lower degree
    a[fl] = np.eye(degree + 1)
    out = []
    for y in (amp, phase):
        b = np.swapaxes(np.swapaxes(kern[..., None] * x, 1, 2) @ (wf * y.reshape(len(gains), -1)), 1, 2)
        b = b.reshape(shape + (degree + 1,))
        out.append(np.linalg.solve(a, b[..., None])[..., 0, 0])
    g = np.exp(out[0] + 1j * out[1])
    return np.where(fl, 0, g), fl
