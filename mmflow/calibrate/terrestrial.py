"""Terrestrial interference and common-mode pickup: rank-1 templates fitted per integration.

Paper section 5.4. Sources that do not move with the sky (cross-talk, common-mode pickup, a
near-field RFI emitter) survive a > 24 h average of the visibilities with the phase centre at
zenith (drift-scan data as stored), while the sky smears into rings of constant declination:

1. ``A = sum_t w_t v_t / sum_t w_t`` per baseline and pol (:func:`zenith_average`);
2. K "dummy sources" at zenith (model coherency ``M_ij = 1``) are peeled from ``A``
   (:func:`mmflow.calibrate.peel.peel_dense`, guard off); their DD gains absorb each pattern,
   so template k is ``B_k,ij = u_ki conj(u_kj)`` (rank 1). Component k starts from the leading
   eigenvector of what the previous components left (autocorrelations zeroed);
3. per integration and pol, real amplitudes of the templates' basis ``B_k`` (K^2 of them, below)
   by weighted least squares on the baselines kept (default > 15 wavelengths)::

       sum_l Re<B_k, B_l>_w a_l(t) = Re<B_k, v_t>_w

   and ``v_t <- v_t - sum_k a_k(t) B_k`` (:func:`subtract_templates`).

The reference implementation runs two passes (fit, subtract, peel the sky, add back, fit again
on the peeled data); the stage composes them from these kernels. Contamination of a map by a
template is measured by ``||B^H v|| / (||B|| ||v||)`` (:func:`projection_fraction`; the paper
found ~0.035 for its three components).

For K > 1 the average fixes the span of the patterns but not their split into rank-1 terms when
they overlap (``sum_k u_k u_k^H`` is invariant under a unitary mixing of the ``u_k``): a constant
cross-talk ``c c^H`` and a flickering emitter ``a(t) e e^H`` are then mixtures of the fitted
``u_k``, with cross terms ``u_k u_l^H``. So the amplitudes are fitted on the K^2 real-coefficient
Hermitian basis of that span (:func:`template_basis`): ``u_k u_k^H``, then for k < l
``u_k u_l^H + u_l u_k^H`` and ``i (u_k u_l^H - u_l u_k^H)``; any ``sum a_kl u_k u_l^H`` with a
Hermitian ``a`` is a real combination of them. For K = 1 it is the single ``u u^H``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmflow.calibrate.baselines import check_pairs, to_matrix
from mmflow.calibrate.peel import PEEL, peel_dense


def zenith_average(vis, weights):
    """Weighted time average (bl, pol) and its summed weight (bl, pol)."""
    w = np.broadcast_to(weights, np.shape(vis)).astype(float)
    ws = w.sum(0)
    v = np.where(w > 0, vis, 0)
    return np.where(ws > 0, (w * v).sum(0) / np.where(ws > 0, ws, 1), 0), ws


def template_basis(patterns, pairs):
    """The real-coefficient Hermitian basis (K^2, bl, pol) of the span of K patterns (K, n_ant, pol).

    ``B = u_k,i conj(u_k,j)`` for each k, then for k < l ``u_k,i conj(u_l,j) + u_l,i conj(u_k,j)``
    and ``i (u_k,i conj(u_l,j) - u_l,i conj(u_k,j))`` on every baseline ``(i, j)`` of ``pairs``.
    """
    pairs = np.asarray(pairs)
    ui, uj = patterns[:, pairs[:, 0]], np.conj(patterns[:, pairs[:, 1]])  # (K, bl, pol)
    K = patterns.shape[0]
    out = [ui[k] * uj[k] for k in range(K)]
    for k in range(K):
        for m in range(k + 1, K):
            kl, lk = ui[k] * uj[m], ui[m] * uj[k]
            out += [kl + lk, 1j * (kl - lk)]
    return np.stack(out)


@dataclass
class Templates:
    """``templates`` (K^2, bl, pol): :func:`template_basis` of ``patterns`` (K, n_ant, pol), the vectors u."""

    templates: np.ndarray
    patterns: np.ndarray
    iterations: np.ndarray


def fit_templates(mean_vis, mean_weights, pairs, n_ant, n_components=3, *, baseline_keep=None, passes=5,
                  tol=1e-8, max_iter=500, threads=None):
    """K rank-1 patterns of the stationary part of ``mean_vis`` (bl, pol) and their templates' basis
    (see the module docstring)."""
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
    u = np.moveaxis(res.dd_gains, 1, -1)  # (K, N, P)
    return Templates(template_basis(u, pairs), u, res.iterations)


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
