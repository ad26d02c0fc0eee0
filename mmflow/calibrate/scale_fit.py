"""Joint flux scales of sources fitted beside peeling: the normal equations per solution.

Per solution (an integration and polarisation's Hermitian antenna matrix), the scales ``a_t`` of
the selected sources' models ``M_t`` minimise ``|| R + sum_t (a_t^old - a_t) M_t ||_w^2``:

    sum_t A_st a_t = Re<M_s, R>_w + sum_t A_st a_t^old,   A_st = Re<M_s, M_t>_w,
    <X, Y>_w = sum_ij w_ij conj(X_ij) Y_ij

(autocorrelations never enter). The Gram matrix depends only on the models, weights and
selection, so :func:`scale_system` forms it (and its Jacobi-scaled pseudo-inverse) once per batch
and :func:`fit_scales` reuses it in every pass of :func:`mmflow.calibrate.peel.peel_dense`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ScaleSystem:
    """The normal equations of :func:`fit_scales` for fixed models, weights and selection: the
    sources ``idx`` (the run from the first selected to the last), their models as rows ``X``
    (S, n, N^2) (a view of the models where they are contiguous), the weights ``w`` (S, N^2) (0 on
    the autocorrelations), the Gram matrix ``A`` (S, n, n), the Jacobi scaling ``d``, the fitted
    entries ``use`` (S, n) and the pseudo-inverse ``P`` of the scaled matrix. Only the right-hand
    side changes between passes."""

    idx: np.ndarray
    sel: np.ndarray
    X: np.ndarray
    w: np.ndarray
    A: np.ndarray
    d: np.ndarray
    use: np.ndarray
    P: np.ndarray


#: matrix entries per block of the Gram matrix's accumulation: a block's weighted models stay in cache
GRAM_BLOCK = 512


def _model_rows(coherencies, idx, dtype):
    """The models of the consecutive sources ``idx`` as rows (S, n, N^2): a view of a C-contiguous
    stack already in ``dtype`` (the stage's), else a copy."""
    S, N = coherencies.shape[1], coherencies.shape[2]
    if isinstance(coherencies, np.ndarray) and coherencies.flags.c_contiguous and coherencies.dtype == dtype:
        return coherencies[idx[0]:idx[-1] + 1].reshape(len(idx), S, N * N).swapaxes(0, 1)
    X = np.empty((S, len(idx), N * N), dtype)
    for a, s in enumerate(idx):
        X[:, a] = np.asarray(coherencies[s]).reshape(S, N * N)
    return X


def scale_system(coherencies, W, sel, dtype):
    """:class:`ScaleSystem` of the sources selected in ``sel`` (n_src, S) (None when none is).

    The Gram matrix ``A_st = Re <M_s, M_t>_w`` per solution is accumulated over blocks of
    :data:`GRAM_BLOCK` matrix entries (real dot products of the (re, im) views, one small GEMM per
    solution and block): no weighted copy of the models is kept."""
    chosen = np.flatnonzero(sel.any(1))
    if len(chosen) == 0:
        return None
    # the run of sources from the first selected to the last: a view of a contiguous stack; a source
    # in between that is selected nowhere (below the horizon all batch) is never fitted (``use``)
    idx = np.arange(chosen[0], chosen[-1] + 1)
    S, N = W.shape[0], W.shape[1]
    n = len(idx)
    X = _model_rows(coherencies, idx, dtype)
    real = np.dtype(dtype).type(0).real.dtype
    w = np.array(np.reshape(W, (S, N * N)), real)
    w[:, :: N + 1] = 0.0  # autocorrelations never enter a fit
    A = np.zeros((S, n, n))
    for c0 in range(0, N * N, GRAM_BLOCK):
        xc = X[:, :, c0:c0 + GRAM_BLOCK]
        xw = (xc * w[:, None, c0:c0 + GRAM_BLOCK]).view(real)
        A += np.matmul(xw, np.swapaxes(xc.view(real), 1, 2))
    diag = np.einsum("sii->si", A)
    # fitted in a solution: selected there, with a model that is not ~0 (a source at the horizon)
    chosen = sel[idx].T
    use = chosen & (diag > 1e-12 * np.max(np.where(chosen, diag, 0.0), axis=1, keepdims=True)) & (diag > 0)
    d = np.where(use, 1 / np.sqrt(np.where(use, diag, 1)), 0.0)  # Jacobi scaling: cond of the correlations
    An = A * d[:, :, None] * d[:, None, :] + np.eye(n) * ~use[:, :, None]
    return ScaleSystem(idx, np.asarray(sel, bool), X, w, A, d, use, np.linalg.pinv(An, rcond=1e-10, hermitian=True))


def fit_scales(R, coherencies, W, scale, sel, system=None):
    """Joint least-squares flux scales of the sources ``sel`` (n_src, S), in place.

    With ``a`` the scales held (0 where not selected), solves per solution the normal equations of
    the selected sources for the data with them put back, ``R + sum_t a_t M_t``,

    ``sum_t A_st a'_t = Re<M_s, R>_w + sum_t A_st a_t``   (``A_st = Re<M_s, M_t>_w``,
    ``<X, Y>_w = sum_ij w_ij conj(X_ij) Y_ij``),

    and updates ``R += sum_t (a_t - a'_t) M_t`` (one pass over the models: the data with the sources
    put back are never formed). Solving them together, not one after another, keeps sources whose
    fringes overlap (low elevations, few baselines) from absorbing each other's flux. The system
    is solved scaled to unit diagonal (the sources' fringe correlations) by a pseudo-inverse
    (singular values below 1e-10 dropped: fully correlated fringes share their flux); a source
    whose model is ~0 there (at the horizon) keeps the scale it had. ``system``: the
    :func:`scale_system` of these models, weights and ``sel``, built once for several passes.
    """
    if not R.flags.c_contiguous:
        raise ValueError("fit_scales updates R in place through a flat view: R must be C-contiguous")
    sys_ = scale_system(coherencies, W, sel, R.dtype) if system is None else system
    if sys_ is None:
        return
    if not np.array_equal(sys_.sel, sel):
        raise ValueError("fit_scales: the system was built for another selection")
    idx, X, d, use = sys_.idx, sys_.X, sys_.d, sys_.use
    S = R.shape[0]
    Rf = R.reshape(S, -1)  # a view: R changes in place
    real = Rf.real.dtype
    start = np.where(sel[idx], scale[idx], 0.0).T  # (S, n)
    rw = (Rf * sys_.w).view(real)[..., None]  # the weights on the residual (1/n of the models' size)
    b = np.matmul(X.view(real), rw)[..., 0].astype(float) + np.matmul(sys_.A, start[..., None])[..., 0]
    new = d * (sys_.P @ (b * d)[..., None])[..., 0]
    for a, s in enumerate(idx):
        fitted = use[:, a]
        scale[s][fitted] = new[fitted, a]
    delta = (start - np.where(sel[idx], scale[idx], 0.0).T).astype(R.dtype)
    Rf += np.matmul(delta[:, None, :], X)[:, 0]
