"""Baseline-list <-> antenna-matrix conversion, gain products and baseline selections.

Visibilities are stored per baseline ``(..., n_bl)`` with an antenna ``pairs`` array
``(n_bl, 2)``; the solvers work on Hermitian antenna matrices ``X[..., i, j] = V_ij``,
``X[..., j, i] = conj(V_ij)``. Gains enter as ``V_ij = g_i conj(g_j) M_ij`` (the convention
``V_ij = <E_i E_j*>``).
"""
from __future__ import annotations

import numba
import numpy as np

from mmflow.errors import InputError
from mmflow.conventions import SPEED_OF_LIGHT


def check_pairs(pairs, n_ant):
    """Validate ``pairs`` (n_bl, 2) of antenna indices; return it as an int array."""
    pairs = np.asarray(pairs)
    if pairs.ndim != 2 or pairs.shape[1] != 2:
        raise InputError("visibilities", "pairs", f"shape {pairs.shape} is not (n_bl, 2)",
                         "give one (i, j) antenna index pair per baseline")
    if pairs.size and (pairs.min() < 0 or pairs.max() >= n_ant):
        raise InputError("visibilities", "pairs", f"antenna index outside 0..{n_ant - 1}",
                         "give n_ant covering every antenna index in pairs")
    return pairs.astype(np.intp)


def to_matrix(vis, pairs, n_ant, fill=0.0, out=None):
    """Baseline axis (last) -> Hermitian antenna matrices ``(..., n_ant, n_ant)``.

    ``X[..., j, i] = conj(V_ij)``, then ``X[..., i, j] = V_ij`` (so an autocorrelation keeps ``V_ii``);
    entries not covered by ``pairs`` are ``fill``. For real input (weights) the matrix is
    symmetric. ``out``: an array of that shape to fill (its dtype kept), e.g. one slice of a
    stack of sources' matrices, which then needs no copy (at 256 antennas a stack of eleven
    sources' matrices is ~0.4 GB per 16 integrations). One compiled pass per matrix (numba), faster
    than numpy's two fancy-indexed scatters (docs/performance.md).
    """
    vis = np.asarray(vis)
    pairs = check_pairs(pairs, n_ant)
    if vis.ndim == 0 or vis.shape[-1] != len(pairs):
        raise ValueError(
            f"visibilities of shape {vis.shape}: the last axis must hold the {len(pairs)} baselines of pairs"
        )
    shape = vis.shape[:-1] + (n_ant, n_ant)
    if out is None:
        out = np.empty(shape, vis.dtype)
    elif out.shape != shape or not out.flags.c_contiguous:
        raise ValueError(f"out has shape {out.shape} (C-contiguous: {out.flags.c_contiguous}), the "
                         f"matrices {shape}")
    if np.iscomplexobj(vis) and not np.iscomplexobj(out):
        raise ValueError(f"complex visibilities cannot fill {out.dtype} matrices")
    rows = np.ascontiguousarray(vis.reshape(-1, vis.shape[-1]), out.dtype)
    i, j = (np.ascontiguousarray(c, np.int64) for c in pairs.T)
    _scatter_hermitian(rows, i, j, out.dtype.type(fill), out.reshape(-1, n_ant, n_ant))
    return out


@numba.njit(nogil=True, cache=True)
def _scatter_hermitian(rows, i, j, fill, out):
    """``out[r] = fill``, ``out[r, j_k, i_k] = conj(rows[r, k])`` for every k, then
    ``out[r, i_k, j_k] = rows[r, k]``."""
    n = out.shape[1]
    for r in range(rows.shape[0]):
        m = out[r]
        for a in range(n):
            for b in range(n):
                m[a, b] = fill
        for k in range(rows.shape[1]):
            m[j[k], i[k]] = np.conj(rows[r, k])
        for k in range(rows.shape[1]):
            m[i[k], j[k]] = rows[r, k]


def solution_matrices(x, pairs, n_ant, out=None):
    """``(time, bl, pol)`` -> ``(time * pol, n_ant, n_ant)``: one Hermitian antenna matrix per
    integration and polarisation (solution ``s = t * n_pol + p``, :func:`to_matrix`, ``out`` as there)."""
    x = np.asarray(x)
    T, B, P = x.shape
    return to_matrix(np.moveaxis(x, -1, 1).reshape(T * P, B), pairs, n_ant, out=out)


def from_matrix(mat, pairs):
    """Antenna matrices ``(..., n_ant, n_ant)`` -> baseline axis ``(..., n_bl)``."""
    pairs = np.asarray(pairs)
    return mat[..., pairs[:, 0], pairs[:, 1]]


def baseline_mask(pairs, enu, freq_hz, min_lambda=15.0, autos=False):
    """Baselines used by a solve: ``|x_j - x_i| / lambda >= min_lambda`` (3-D length).

    Autocorrelations (``i == j``) are excluded unless ``autos``; they have zero length, so a
    positive ``min_lambda`` excludes them anyway.
    """
    pairs = np.asarray(pairs)
    keep = baseline_lengths(pairs, enu, freq_hz) >= min_lambda
    if not autos:
        keep &= pairs[:, 0] != pairs[:, 1]
    else:
        keep |= pairs[:, 0] == pairs[:, 1]
    return keep



#: the cut ``auto`` never exceeds (wavelengths): beyond the diffuse Galactic emission's scales at
#: the paper's frequencies (the paper solves on baselines longer than ~15 lambda)
AUTO_MAX_LAMBDA = 15.0
#: the fewest cross baselines a solve keeps per antenna (fewer when the antenna has fewer)
MIN_BASELINES_PER_ANTENNA = 3


def baseline_lengths(pairs, enu, freq_hz):
    """Baseline lengths in wavelengths, ``|x_j - x_i| / lambda`` (3-D), per pair."""
    pairs = np.asarray(pairs)
    return np.linalg.norm(enu[pairs[:, 1]] - enu[pairs[:, 0]], axis=1) * freq_hz / SPEED_OF_LIGHT


def _required(n_cross, keep_fraction):
    """Cross baselines each antenna must keep: ``max(ceil(f n), min(3, n))`` of its ``n``."""
    return np.maximum(np.ceil(keep_fraction * n_cross), np.minimum(MIN_BASELINES_PER_ANTENNA, n_cross)).astype(int)


def auto_min_lambda(pairs, enu, freq_hz, cap=AUTO_MAX_LAMBDA, keep_fraction=0.5):
    """The ``auto`` baseline cut: ``min(cap, min_a L_a)``, where ``L_a`` is the length (wavelengths)
    of antenna a's ``k_a``-th longest cross baseline and ``k_a = max(ceil(keep_fraction n_a),
    min(3, n_a))`` of its ``n_a`` cross baselines.

    Every antenna then keeps at least ``k_a`` baselines (at least half of its own), and on an
    extended array (the OVRO-LWA at 30-80 MHz) the cut is the paper's 15 lambda: the short
    baselines, where the unmodelled diffuse sky dominates, are left out of the solve only as far
    as the layout allows. A compact array (40 stands within 70 m at 52 MHz, longest baseline
    ~12 lambda) gets ~4 lambda instead of a cut that leaves most antennas without a baseline.
    """
    lengths = baseline_lengths(pairs, enu, freq_hz)
    pairs = np.asarray(pairs)
    cross = pairs[:, 0] != pairs[:, 1]
    cut = float(cap)
    for a in np.unique(pairs[cross]):
        mine = np.sort(lengths[cross & ((pairs[:, 0] == a) | (pairs[:, 1] == a))])
        k = int(_required(np.array([mine.size]), keep_fraction)[0])
        cut = min(cut, float(mine[mine.size - k]))
    return cut


def resolve_min_lambda(setting, pairs, enu, freq_hz):
    """A ``min_baseline_lambda`` setting as a number: ``"auto"`` -> :func:`auto_min_lambda`."""
    return auto_min_lambda(pairs, enu, freq_hz) if setting == "auto" else float(setting)


def antennas_short_of_baselines(pairs, enu, freq_hz, min_lambda):
    """``(antennas, kept, required)``: antenna indices (of those with cross baselines in ``pairs``)
    keeping fewer than ``min(3, n_a)`` cross baselines at the cut ``min_lambda``, with how many
    each keeps and needs."""
    pairs = np.asarray(pairs)
    cross = pairs[:, 0] != pairs[:, 1]
    keep = baseline_mask(pairs, enu, freq_hz, min_lambda) & cross
    n_ant = int(pairs.max()) + 1 if pairs.size else 0

    def per_antenna(mask):
        return np.bincount(pairs[mask, 0], minlength=n_ant) + np.bincount(pairs[mask, 1], minlength=n_ant)

    n, kept = per_antenna(cross), per_antenna(keep)
    need = np.minimum(MIN_BASELINES_PER_ANTENNA, n)
    short = np.flatnonzero((n > 0) & (kept < need))
    return short, kept[short], need[short]


def antennas_with_data(weights, pairs, n_ant, keep=None):
    """``(n_ant, n_pol)`` bool: antenna a has a weighted sample on a used cross baseline.

    ``weights`` is ``(..., n_bl, n_pol)``; ``keep`` (n_bl,) the baselines a solve uses."""
    pairs = np.asarray(pairs)
    w = np.asarray(weights)
    used = (pairs[:, 0] != pairs[:, 1]) if keep is None else (np.asarray(keep, bool) & (pairs[:, 0] != pairs[:, 1]))
    any_w = (w > 0).reshape(-1, *w.shape[-2:]).any(axis=0) & used[:, None]  # (n_bl, n_pol)
    out = np.zeros((n_ant, w.shape[-1]), bool)
    for p in range(w.shape[-1]):
        b = np.flatnonzero(any_w[:, p])
        out[pairs[b, 0], p] = True
        out[pairs[b, 1], p] = True
    return out
