"""The cross hands xy, yx of what the parallel hands' solutions remove: peeled and subtracted sources,
terrestrial templates.

Correlations (docs/conventions.md): ``xy_ij = V_(ix),(jy)`` and ``yx_ij = V_(iy),(jx)``, feed ``p`` of
antenna ``i`` with feed ``q`` of antenna ``j``, entries of the Hermitian ``2N x 2N`` feed-antenna
coherency ``V``; so ``yx_ij = conj(V_(jx),(iy))``: the cross block ``X = [V_(ix),(jy)]`` holds xy on
and above its diagonal and ``conj(yx)`` (transposed) below.

A component that the parallel hands model as ``h_ip conj(h_jp) M_ij,pp`` (a source's DD gains ``h``
per antenna and feed, its model ``M`` through the E-field beam, ``M_ij,pq = sum J_p S J_q^H e^{2 pi i
b . r / lambda}``; or a terrestrial pattern ``u_kp,i conj(u_lp,j)``) has, in the cross hands::

    xy_ij = c h_ix conj(h_jy) M_ij,xy = c T_ij,xy,      yx_ij = conj(c) h_iy conj(h_jx) M_ij,yx = conj(c) T_ij,yx

with one complex ``c`` per component and integration. The parallel hands fix ``h_ip`` only up to a
constant phase per feed (``h_ip conj(h_jp)`` does not see it), and ``calibrate`` leaves the same
freedom in the direction-independent gains (the XY phase, not calibrated): ``c`` is that phase
difference (and what is left of the amplitudes), ``|c| ~ 1``. Its conjugate on yx is Hermiticity:
``yx_ij = conj(X_ji)``. A terrestrial signal with coherency ``sum_r e_r e_r^H`` over the feeds has
parallel blocks spanned by the fitted patterns ``u_kx``, ``u_ky``, so its cross block is ``sum_kl a_kl
u_kx u_ly^H``: the templates ``T^kl_ij,xy = u_kx,i conj(u_ly,j)``, ``T^kl_ij,yx = u_ly,i conj(u_kx,j)``.

The coefficients of all components of an integration are one complex weighted least-squares fit of
xy and ``conj(yx)`` together (:func:`fit_cross`)::

    min_c  sum_b w^xy_b |xy_b - sum_s c_s T^s_b,xy|^2 + w^yx_b |conj(yx_b) - sum_s c_s conj(T^s_b,yx)|^2

    =>  sum_s' G_ss' c_s' = r_s,   G_ss' = sum_b w^xy conj(T^s_xy) T^s'_xy + w^yx T^s_yx conj(T^s'_yx),
                                   r_s   = sum_b w^xy conj(T^s_xy) xy + w^yx T^s_yx conj(yx)

(a component not active in an integration gets ``c = 0``), and :func:`cross_model` is
``(sum_s c_s T^s_xy, sum_s conj(c_s) T^s_yx)``. A component whose cross hands are weak (a source near
the zenith, or where ``J_x . J_y`` vanishes, at azimuths 0 and 90 deg for short dipoles) makes ``G``
near-singular, and ``c`` would take any size; ``ridge`` adds ``lambda_s`` to ``G_ss``
(``c_s -> 0`` where ``G_ss << lambda_s``: what is left in the cross hands is then below
``sqrt(lambda_s)`` of the fit's scale, and nothing is subtracted that the data do not measure).
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import CROSS_FEEDS
from mmflow.simulate.corrupt import gain_products

#: the largest ``|c_s| / |c_bar|`` :func:`fit_cross_bounded` accepts: the amplitudes the parallel hands fit
#: leave ``|c|`` within a few tens of percent of 1 (scintillation, the XY amplitude ratio)
CROSS_MAX_RATIO = 3.0


def gain_templates(models, gains, pairs):
    """``T`` (n, time, bl, 2) of components with DD gains: ``h_ip conj(h_jq) M_ij,pq`` for (pq) = xy, yx.

    Parameters
    ----------
    models : ndarray (n, time, bl, 2): each component's model in xy, yx (Jy)
    gains : ndarray (n, time, n_ant, 2) per feed x, y, or None (1: a component at its catalogue position)
    pairs : ndarray (bl, 2)
    """
    if gains is None:
        return np.asarray(models)
    return models * gain_products(gains, pairs, CROSS_FEEDS)


def pattern_templates(patterns, pairs):
    """``T`` (K^2, bl, 2) of K terrestrial patterns (K, n_ant, 2 feeds): ``T^kl_xy = u_kx,i conj(u_ly,j)``,
    ``T^kl_yx = u_ly,i conj(u_kx,j)``, in the order ``k * K + l``."""
    pairs = np.asarray(pairs)
    ux, uy = patterns[..., 0], patterns[..., 1]  # (K, n_ant)
    i, j = pairs[:, 0], pairs[:, 1]
    xy = ux[:, None, i] * np.conj(uy[None, :, j])  # (k, l, bl)
    yx = uy[None, :, i] * np.conj(ux[:, None, j])
    K = patterns.shape[0]
    return np.stack([xy, yx], axis=-1).reshape(K * K, len(pairs), 2)


def _templates_per_time(templates, vis):
    """``templates`` as (n, time, bl, 2): one set of templates (n, bl, 2) repeated over ``vis``' integrations
    (a view, no copy)."""
    T = np.asarray(templates)
    if T.ndim == 3:
        T = np.broadcast_to(T[:, None], (T.shape[0],) + vis.shape)
    return T


def cross_normal(vis, weights, templates):
    """``G`` (time, n, n) and ``r`` (time, n) of the module's least squares with every component active.

    The design rows of integration ``t`` are ``a_s = [T^s_xy, conj(T^s_yx)]`` (2 bl of them), the data
    ``d = [xy, conj(yx)]`` (0 where the weight is 0), so ``G_t = conj(A_t) W_t A_t^T`` and
    ``r_t = conj(A_t) W_t d_t`` for ``A_t`` (n, 2 bl): one complex GEMM per integration (BLAS), where a
    contraction over three indices would run in numpy's own loops.

    Parameters
    ----------
    vis : ndarray (time, bl, 2): xy, yx
    weights : ndarray broadcastable to ``vis`` (0: not used)
    templates : ndarray (n, time, bl, 2) or (n, bl, 2) (the same in every integration)
    """
    vis = np.asarray(vis)
    T = _templates_per_time(templates, vis)
    n, n_t, n_bl = T.shape[:3]
    w = np.broadcast_to(weights, vis.shape)
    wd = np.concatenate([w[..., 0], w[..., 1]], axis=-1)  # (time, 2 bl)
    ah = np.empty((n_t, n, 2 * n_bl), complex)  # conj(A_t), built in place: the templates' size, twice
    np.conjugate(np.moveaxis(T[..., 0], 0, 1), out=ah[..., :n_bl])
    ah[..., n_bl:] = np.moveaxis(T[..., 1], 0, 1)
    aw = np.conj(ah)
    aw *= wd[:, None]
    G = ah @ np.swapaxes(aw, 1, 2)
    del aw
    d = np.concatenate([vis[..., 0], np.conj(vis[..., 1])], axis=-1)
    d = np.where(wd > 0, d, 0) * wd
    return G, (ah @ d[..., None])[..., 0]


def solve_cross(G, r, active=None, ridge=None, prior=None):
    """Coefficients (time, n) from :func:`cross_normal`'s ``G``, ``r``: ``(G + Lambda) c = r + Lambda c_prior``
    over the ``active`` components of each integration (the others: 0).

    Parameters
    ----------
    G : ndarray (time, n, n); r : ndarray (time, n)
    active : bool ndarray (n, time), optional: the components fitted in each integration
    ridge : ndarray broadcastable to (time, n), optional: ``lambda`` added to ``G``'s diagonal
    prior : ndarray broadcastable to (time, n), optional: what the ridge draws ``c`` towards (default 0)
    """
    G = np.array(G, complex)
    r = np.array(r, complex)
    if active is not None:  # an inactive component's design row is 0: its rows and columns of G, its r
        m = np.asarray(active, bool).T
        G *= m[:, :, None] & m[:, None, :]
        r *= m
    diag = np.arange(G.shape[1])
    if ridge is not None:
        ridge = np.broadcast_to(ridge, G.shape[:2]) * (1 if active is None else np.asarray(active, bool).T)
        G[:, diag, diag] += ridge
        if prior is not None:
            r = r + ridge * prior
    empty = np.abs(G[:, diag, diag]) == 0  # nothing to fit: c = 0
    G[:, diag, diag] += empty
    return np.linalg.solve(G, r[..., None])[..., 0]


def fit_cross(vis, weights, templates, active=None, ridge=None, prior=None):
    """Complex coefficients (time, n) of the components in the cross hands (the module's least squares):
    :func:`solve_cross` of :func:`cross_normal`.

    Parameters
    ----------
    vis : ndarray (time, bl, 2): xy, yx
    weights : ndarray broadcastable to ``vis`` (0: not used, e.g. autocorrelations, short baselines)
    templates : ndarray (n, time, bl, 2) or (n, bl, 2) (the same in every integration)
    active : bool ndarray (n, time), optional: the components fitted in each integration (others: 0)
    ridge : ndarray broadcastable to (time, n), optional: ``lambda`` added to ``G``'s diagonal
    prior : ndarray broadcastable to (time, n), optional: what the ridge draws ``c`` towards (default 0),
        ``(G + Lambda) c = r + Lambda c_prior``
    """
    return solve_cross(*cross_normal(vis, weights, templates), active, ridge, prior)


def fit_cross_bounded(vis, weights, templates, active=None, ridge=None, max_ratio=CROSS_MAX_RATIO):
    """:func:`fit_cross` with every coefficient bounded: ``(c (time, n), refused (time, n) bool)``.

    Physically ``c_s`` is the XY phase, common to every direction, times what is left of the amplitudes
    (``|c_s| ~ 1``). A component whose cross-hand template the data barely measure (a source low in the
    beam, or whose template is nearly a combination of the others') can otherwise take any coefficient
    (``|c|`` up to 1e13 was met: it removes the data's projection on that template). So:

    1. ``c_bar`` (time,): one coefficient shared by the active components, fitted against ``sum_s T^s``
       (the common XY phase; dominated by the brightest sources);
    2. ``c_s`` by the joint fit with ``ridge`` drawing each towards ``c_bar`` instead of 0, so a component
       the data do not measure gets the common coefficient;
    3. a coefficient with ``|c_s| > max_ratio |c_bar|`` is refused: set to ``c_bar`` (its template then
       subtracted at the common coefficient) and the others refitted without it, until none is refused.

    All three are solved from one :func:`cross_normal` (``G``, ``r`` of every component): the shared
    template's are ``m^T G m`` and ``m . r`` (``m`` the active components), and subtracting the refused
    components' fixed ``c_fix`` from the data is ``r - G c_fix``.

    Returns the coefficients and the refused components (for the summary: the data did not measure
    them).
    """
    vis = np.asarray(vis)
    T = _templates_per_time(templates, vis)
    n, n_t = T.shape[0], vis.shape[0]
    act = np.ones((n, n_t), bool) if active is None else np.asarray(active, bool).copy()
    G, r = cross_normal(vis, weights, T)
    m = act.T.astype(float)  # (time, n)
    g_bar = np.einsum("ts,tsk,tk->t", m, G, m)
    c_bar = solve_cross(g_bar[:, None, None], np.einsum("ts,ts->t", m, r)[:, None])[:, 0]  # (time,)
    lam = np.zeros((n_t, n)) if ridge is None else np.broadcast_to(ridge, (n_t, n))
    refused = np.zeros((n_t, n), bool)
    for _ in range(n):
        free = act & ~refused.T
        fixed = np.where(refused, c_bar[:, None], 0.0) * act.T  # (time, n)
        c = solve_cross(G, r - (G @ fixed[..., None])[..., 0], free, lam, c_bar[:, None]) + fixed
        new = free.T & (np.abs(c) > max_ratio * np.abs(c_bar)[:, None])
        if not new.any():
            return c, refused
        refused |= new
    return c, refused


def cross_model(coefficients, templates):
    """``sum_s c_s T^s_xy``, ``sum_s conj(c_s) T^s_yx``: (time, bl, 2) for ``coefficients`` (time, n) and
    ``templates`` (n, time, bl, 2) or (n, bl, 2)."""
    c = np.asarray(coefficients)
    T = np.asarray(templates)
    sub = "tn,nbp->tbp" if T.ndim == 3 else "tn,ntbp->tbp"
    xy = np.einsum(sub, c, T[..., :1])
    yx = np.einsum(sub, np.conj(c), T[..., 1:])
    return np.concatenate([xy, yx], axis=-1)
