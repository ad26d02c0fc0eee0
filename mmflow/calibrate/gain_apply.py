"""Gains applied to visibilities and autocorrelations: the corrections every later reader makes.

A corrected visibility is

    V'_ij,pq = V_ij,pq / (g_ip conj(g_jq)) = V_ij,pq (1 / g_ip) conj(1 / g_jq)

(baseline ``ij``, feed ``p`` of antenna ``i`` and ``q`` of antenna ``j``), with weight 0 and data 0
where an end is flagged or has no gain. :func:`apply_gains` does it in one compiled pass over the
data (every stage after ``calibrate`` reads its data through it: at 256 antennas a time chunk is
8.4M baselines x 2 polarisations, and numpy's version spent ~1.2 s on gathers, a boolean scatter
and copies of it).
"""
from __future__ import annotations

import numba
import numpy as np


def apply_gains(vis, weights, pairs, gains, flags=None, feeds=None, out=None):
    """Correct visibilities: ``V_ij,pq / (g_ip conj(g_jq))``, computed as ``V_ij,pq (1 / g_ip)
    conj(1 / g_jq)``; flagged antennas (and gains of 0) get weight 0 and data 0.

    Parameters
    ----------
    vis : ndarray (time, bl, pol)
    weights : ndarray broadcastable to ``vis``
    pairs : ndarray (bl, 2) antenna indices ``(i, j)``
    gains : ndarray (time, n_ant, feed) or (n_ant, feed)
    flags : bool array like ``gains``, optional
    feeds : pair of sequences, optional
        ``(p, q)``: polarisation k of ``vis`` correlates feed ``p[k]`` of antenna i with feed
        ``q[k]`` of antenna j (the cross hands xy, yx: ``((0, 1), (1, 0))``). Default: ``p = q``
        = the polarisation axis itself (the parallel hands, one gain per feed).
    out : pair of ndarrays (time, bl, pol), optional
        Where the corrected visibilities and weights go; ``(vis, weights)`` themselves corrects in
        place (each sample is read before it is written). At 256 antennas new arrays for a time
        chunk cost more in first-touch page faults (~0.7 s) than the correction itself (~0.1 s).

    Returns
    -------
    (vis_corrected, weights_out): ``out``, or new arrays of ``vis``'s dtype and of the dtype of
    ``weights`` with a float; the inputs are not modified unless they are ``out``.
    """
    pairs = np.asarray(pairs)
    vis = np.asarray(vis)
    if vis.ndim != 3:
        raise ValueError(f"apply_gains: visibilities of shape {vis.shape}, not (time, baseline, pol)")
    T, B, P = vis.shape
    # the reciprocal gains once per antenna (0 for a gain of 0): the data are multiplied, not divided
    gains = np.asarray(gains)
    inv = np.divide(1.0, gains, out=np.zeros(gains.shape, np.result_type(gains, 1.0)), where=gains != 0)
    if inv.ndim == 2:
        inv = inv[None]
    if inv.shape[0] not in (1, T):
        raise ValueError(f"apply_gains: gains for {inv.shape[0]} integrations, data for {T}")
    flags = np.zeros((1, 1, 1), bool) if flags is None else np.asarray(flags, bool)
    flags = flags.reshape((-1,) + flags.shape[-2:])
    p, q = (np.arange(P), np.arange(P)) if feeds is None else (np.asarray(f, np.int64) for f in feeds)
    weights = np.asarray(weights)
    if out is None:
        out = np.empty(vis.shape, vis.dtype), np.empty(vis.shape, np.result_type(weights.dtype, 0.0))
    out, w_out = out
    if out.shape != vis.shape or w_out.shape != vis.shape:
        raise ValueError(f"apply_gains: out has shapes {out.shape}, {w_out.shape}; the data {vis.shape}")
    _correct(vis, np.broadcast_to(weights, vis.shape), np.broadcast_to(inv, (T,) + inv.shape[1:]),
             np.broadcast_to(flags, (T,) + inv.shape[1:]), np.ascontiguousarray(pairs[:, 0], np.int64),
             np.ascontiguousarray(pairs[:, 1], np.int64), np.asarray(p, np.int64), np.asarray(q, np.int64), out, w_out)
    return out, w_out


@numba.njit(nogil=True, cache=True)
def _correct(vis, weights, inv, flags, i, j, p, q, out, w_out):
    """``out[t, b, k] = vis[t, b, k] (inv[t, i_b, p_k] conj(inv[t, j_b, q_k]))`` and the weight, or 0 and
    weight 0 where that factor is 0 or an end is flagged (the factor formed first, as numpy would)."""
    for t in range(vis.shape[0]):
        for b in range(vis.shape[1]):
            a, c = i[b], j[b]
            for k in range(vis.shape[2]):
                f = inv[t, a, p[k]] * np.conj(inv[t, c, q[k]])
                if f == 0 or flags[t, a, p[k]] or flags[t, c, q[k]]:
                    out[t, b, k] = 0
                    w_out[t, b, k] = 0
                else:
                    out[t, b, k] = vis[t, b, k] * f
                    w_out[t, b, k] = weights[t, b, k]


def apply_gains_autos(autos, gains, flags=None):
    """Autocorrelation powers in the units of the corrected data: ``|V_ii| / |g_i|^2``.

    The radiometer noise of a corrected visibility, ``sigma_ij^2 = <V_ii> <V_jj> / (dnu tau)``,
    needs the autocorrelations corrected as the visibilities are (:func:`apply_gains` divides
    ``V_ij`` by ``g_i conj(g_j)``); uncorrected, raw data in correlator units would weigh baseline
    ``ij`` by ``|g_i g_j|^2`` and scale every variance by the mean ``|g|^4``.

    Parameters
    ----------
    autos : ndarray (time, n_ant, pol)
        ``|V_ii|`` (NaN where an antenna has none).
    gains, flags
        As :func:`apply_gains`. Antennas flagged or with gain 0 keep their values: their
        baselines already weigh 0.

    Returns
    -------
    ndarray like ``autos`` (the input is not modified).
    """
    amp2 = np.abs(np.broadcast_to(gains, np.shape(autos))) ** 2
    bad = amp2 == 0
    if flags is not None:
        bad = bad | np.broadcast_to(flags, np.shape(autos))
    return np.where(bad, autos, autos / np.where(bad, 1.0, amp2))
