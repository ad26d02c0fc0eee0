"""Terrestrial interference and common-mode pickup: rank-1 templates fitted per integration.

Paper section 5.4. Sources that do not move with the sky (cross-talk, common-mode pickup, a
near-field RFI emitter) survive a > 24 h average of the visibilities with the phase centre at
zenith (drift-scan data as stored), while the sky smears into rings of constant declination:

1. ``A = sum_t w_t v_t / sum_t w_t`` per baseline and pol (:func:`zenith_average`);
2. K "dummy sources" at zenith (model coherency ``M_ij = 1``) are peeled from ``A``
   (:func:`mmflow.calibrate.peel.peel_dense`, guard off); their DD gains absorb each pattern,
   so template k is ``B_k,ij = u_ki conj(u_kj)`` (rank 1). Component k starts from the leading
   eigenvector of what the previous components left (autocorrelations zeroed);
3. per integration and pol, real amplitudes by weighted least squares on the baselines kept
   (default > 15 wavelengths)::

       sum_l Re<B_k, B_l>_w a_l(t) = Re<B_k, v_t>_w

   and ``v_t <- v_t - sum_k a_k(t) B_k`` (:func:`subtract_templates`).

The reference implementation runs two passes (fit, subtract, peel the sky, add back, fit again
on the peeled data); the stage composes them from these kernels. Contamination of a map by a
template is measured by ``||B^H v|| / (||B|| ||v||)`` (:func:`projection_fraction`; the paper
found ~0.035 for its three components).

Note: for K > 1 the span of the templates is determined by the average, but not the split
into rank-1 terms when the patterns overlap (``sum_k u_k u_k^H`` is invariant under a unitary
mixing of the ``u_k``); the leading-eigenvector start picks the strongest pattern first.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmflow.calibrate.baselines import check_pairs, from_matrix, to_matrix
from mmflow.calibrate.peel import PEEL, peel_dense


def zenith_average(vis, weights):
    """Weighted time average (bl, pol) and its summed weight (bl, pol)."""
    w = np.broadcast_to(weights, np.shape(vis)).astype(float)
    ws = w.sum(0)
    v = np.where(w > 0, vis, 0)
    return np.where(ws > 0, (w * v).sum(0) / np.where(ws > 0, ws, 1), 0), ws


@dataclass
class Templates:
    """``templates`` (K, bl, pol) = u_i conj(u_j); ``patterns`` (K, n_ant, pol) the vectors u."""

    templates: np.ndarray
    patterns: np.ndarray
    iterations: np.ndarray


def fit_templates(mean_vis, mean_weights, pairs, n_ant, n_components=3, *, baseline_keep=None, passes=5,
                  tol=1e-8, max_iter=500, threads=None):
    """Rank-1 templates of the stationary part of ``mean_vis`` (bl, pol) (see the module docstring)."""
    pairs = check_pairs(pairs, n_ant)
    P = mean_vis.shape[-1]
    w = np.array(mean_weights, float)
    w[pairs[:, 0] == pairs[:, 1]] = 0
    if baseline_keep is not None:
        w[~np.asarray(baseline_keep, bool)] = 0
    A = to_matrix(np.moveaxis(mean_vis, -1, 0), pairs, n_ant)  # (P, N, N)
    W = to_matrix(np.moveaxis(w, -1, 0), pairs, n_ant)
    K = n_components
    ones = np.ones((K, P, n_ant, n_ant), complex)
    g0 = np.zeros((K, P, n_ant), complex)
    R = A * (W > 0)
    for k in range(K):  # sequential leading eigenvectors as the start
        val, vec = np.linalg.eigh(R)
        u = vec[..., -1] * np.sqrt(np.maximum(val[..., -1], 0))[:, None]
        u[np.abs(u) == 0] = 1e-12
        g0[k] = u
        R = R - u[:, :, None] * np.conj(u)[:, None, :] * (W > 0)
    res = peel_dense(A, ones, W, np.full((K, P), PEEL), g0, passes=passes, tol=tol, max_iter=max_iter,
                     guard=None, threads=threads)
    u = res.dd_gains  # (K, P, N)
    tmpl = from_matrix(u[..., :, None] * np.conj(u)[..., None, :], pairs)  # (K, P, bl)
    return Templates(np.moveaxis(tmpl, 1, -1), np.moveaxis(u, 1, -1), res.iterations)


def fit_amplitudes(vis, weights, templates, baseline_keep=None):
    """Real amplitudes (time, K, pol) of each template per integration, weighted least squares."""
    w = np.array(np.broadcast_to(weights, np.shape(vis)), float)
    if baseline_keep is not None:
        w[:, ~np.asarray(baseline_keep, bool)] = 0
    v = np.where(w > 0, vis, 0)
    B = templates  # (K, bl, pol)
    G = np.einsum("tbp,kbp,lbp->tpkl", w, np.conj(B), B).real
    h = np.einsum("tbp,kbp,tbp->tpk", w, np.conj(B), v).real
    ok = np.abs(np.linalg.det(G)) > 0
    a = np.zeros(h.shape)
    a[ok] = np.linalg.solve(G[ok], h[ok][..., None])[..., 0]
    return np.moveaxis(a, -1, 1)


def subtract_templates(vis, templates, amplitudes):
    """``v_t - sum_k a_k(t) B_k`` on every baseline: (time, bl, pol)."""
    return vis - np.einsum("tkp,kbp->tbp", amplitudes, templates)


def projection_fraction(B, v, ord="fro"):
    """``||B^H v|| / (||B|| ||v||)``: how much of ``v`` a response matrix ``B`` can see.

    ``B`` (n_rows, n_cols) is any response (e.g. an m-mode transfer block), ``v`` (n_rows,) or
    (n_rows, n) the interference; ``ord`` is the matrix norm of B (``"fro"`` or 2).
    """
    B = np.asarray(B)
    v = np.asarray(v)
    return float(np.linalg.norm(B.conj().T @ v) / (np.linalg.norm(B, ord) * np.linalg.norm(v)))
