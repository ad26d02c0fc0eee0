"""Baseline-list <-> antenna-matrix conversion, gain products and baseline selections.

Visibilities are stored per baseline ``(..., n_bl)`` with an antenna ``pairs`` array
``(n_bl, 2)``; the solvers work on Hermitian antenna matrices ``X[..., i, j] = V_ij``,
``X[..., j, i] = conj(V_ij)``. Gains enter as ``V_ij = g_i conj(g_j) M_ij`` (the convention
``V_ij = <E_i E_j*>``).
"""
from __future__ import annotations

import numpy as np

from mmflow.errors import InputError
from mmflow.telescope.array import C_LIGHT


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


def to_matrix(vis, pairs, n_ant, fill=0.0):
    """Baseline axis (last) -> Hermitian antenna matrices ``(..., n_ant, n_ant)``.

    Entries not covered by ``pairs`` are ``fill``. For real input (weights) the matrix is
    symmetric.
    """
    vis = np.asarray(vis)
    pairs = check_pairs(pairs, n_ant)
    out = np.full(vis.shape[:-1] + (n_ant, n_ant), fill, dtype=vis.dtype)
    i, j = pairs[:, 0], pairs[:, 1]
    out[..., j, i] = np.conj(vis) if np.iscomplexobj(vis) else vis
    out[..., i, j] = vis
    return out


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
    length = np.linalg.norm(enu[pairs[:, 1]] - enu[pairs[:, 0]], axis=1) * freq_hz / C_LIGHT
    keep = length >= min_lambda
    if not autos:
        keep &= pairs[:, 0] != pairs[:, 1]
    else:
        keep |= pairs[:, 0] == pairs[:, 1]
    return keep

