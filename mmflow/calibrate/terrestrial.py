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

The per-integration fit takes from the sky whatever of it lies along the templates. Where the
templates resemble the sky (a small array with no terrestrial signal fits the residual sky's m = 0
part, brightest where circumpolar sources stand), a source near them loses a large share:
:func:`direction_loss`, :func:`declination_loss` and :func:`sky_loss` measure that share from the templates and the
array alone, so the stage can keep each template's amplitude constant (its mean over the day: only the
stationary part, which lives at m = 0) where the fit would take too much of a source
(:func:`mean_amplitudes`).

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
from mmflow.conventions import SPEED_OF_LIGHT


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


#: directions whose fringes :func:`direction_loss` forms at a time
DIRECTIONS_PER_BLOCK = 2048


def direction_loss(templates, baselines, weights, directions):
    """Share of a unit point source's weighted power that a per-integration fit of ``templates`` takes, per
    polarisation and direction.

    With ``s_b(r) = exp(2 pi i b . r)`` the source's visibility on baseline ``b`` (in wavelengths, ``x_j -
    x_i``: the data's convention), the real amplitudes' normal matrix ``G = Re(B^H W B)`` and ``h(r) = Re(B^H W
    s(r))``, the fit removes ``B G^-1 h`` and::

        loss(r) = h^T G^-1 h / sum_b w_b

    (the squared norm of the real projection over ``||s||_W^2``; a template ``u u^H`` with ``u_i = exp(-2 pi i
    x_i . r0)`` takes all of a source at ``r0``; templates unrelated to the sky take ``K^2 / (2 n_bl)`` on
    average).

    Parameters
    ----------
    templates : (K^2, bl, pol) complex
    baselines : (bl, 3) baseline vectors in wavelengths
    weights : (bl, pol) the fit's weights (zero on baselines it does not use)
    directions : (n, 3) ENU unit vectors

    Returns
    -------
    (pol, n) float, in [0, 1]
    """
    w = np.asarray(weights, float)
    used = (w > 0).any(-1)
    directions = np.asarray(directions)
    out = np.zeros((w.shape[-1], len(directions)))
    B, b, w = templates[:, used], baselines[used], w[used]
    BW = np.conj(B) * w  # (K^2, bl, pol)
    G = np.einsum("kbp,lbp->pkl", BW, B).real
    total = w.sum(0)
    for i in range(0, len(directions), DIRECTIONS_PER_BLOCK):  # the fringes (bl, block) at most ~70 MB
        fringe = np.exp(2j * np.pi * (b @ directions[i:i + DIRECTIONS_PER_BLOCK].T))  # (bl, block)
        for p in range(w.shape[-1]):
            if total[p] > 0:
                h = (BW[..., p] @ fringe).real  # (K^2, block)
                out[p, i:i + DIRECTIONS_PER_BLOCK] = np.sum(h * np.linalg.lstsq(G[p], h, rcond=None)[0], 0) / total[p]
    return out


def sidereal_tracks(lat_rad, n_dec=90, n_hour=180):
    """ENU unit vectors (n_dec, n_hour, 3) of the tracks of declinations that rise, over one sidereal day.

    ``e = -cos d sin H``, ``n = sin d cos phi - cos d cos H sin phi``, ``u = sin d sin phi + cos d cos H cos
    phi`` at hour angles ``H = 2 pi k / n_hour``, declinations ``d`` evenly between the lowest that rises,
    ``lat - 90 deg`` (``lat + 90`` south of the equator), and the visible pole. Returns (dec (n_dec,), enu).
    """
    south = lat_rad < 0
    lo, hi = (-np.pi / 2, lat_rad + np.pi / 2) if south else (lat_rad - np.pi / 2, np.pi / 2)
    dec = lo + (hi - lo) * (np.arange(n_dec) + 0.5) / n_dec
    H = 2 * np.pi * np.arange(n_hour) / n_hour
    d, h = dec[:, None], H[None, :]
    enu = np.stack([-np.cos(d) * np.sin(h), np.sin(d) * np.cos(lat_rad) - np.cos(d) * np.cos(h) * np.sin(lat_rad),
                    np.sin(d) * np.sin(lat_rad) + np.cos(d) * np.cos(h) * np.cos(lat_rad)], -1)
    return dec, enu


def declination_loss(loss, power):
    """What a source at each declination loses of its map peak: ``sum_t P^2 loss / sum_t P^2`` over its track.

    ``loss`` and ``power`` (n_dec, n_hour) on :func:`sidereal_tracks`: the direction loss and the beam's
    power response (zero below the horizon). A source's peak in the map weighs each integration by the
    square of its response there (a matched filter: its visibilities scale with ``P``). Returns (n_dec,).
    """
    p2 = np.asarray(power, float) ** 2
    total = p2.sum(-1)
    return np.where(total > 0, (p2 * loss).sum(-1) / np.where(total > 0, total, 1), 0.0)


def sky_loss(loss, power):
    """The largest :func:`declination_loss` over the declinations, each weighed by how well the array sees
    them: ``max_d sum_t P^2 loss / max_d sum_t P^2``.

    A declination that only skims the horizon is seen through the beam's last fraction of a percent; relative
    to its own faint track it could lose all of a source to a template of a distant emitter on the horizon,
    which is what the per-integration fit is for. Weighed by its track's power against the best-seen
    declination's, its loss counts as little as the array sees it; a circumpolar or overhead declination
    counts fully.
    """
    seen = (np.asarray(power, float) ** 2).sum(-1)  # each track's sum_t P^2
    best = seen.max()
    return float((declination_loss(loss, power) * seen).max() / best) if best > 0 else 0.0


#: baselines (evenly spaced among those the fit uses) on which :func:`template_sky_loss` measures the loss: it is
#: an average over baselines, and a subset bounds the cost at any array size (``mmflow bench calibrate``'s
#: ``terrestrial_sky_loss``: 0.9-1.7 s a channel of two polarisations at 256 antennas on a 2-core VM)
LOSS_BASELINES = 2048
#: declinations and hour angles of :func:`template_sky_loss`'s tracks
TRACK_POINTS = (60, 120)


def template_sky_loss(patterns, pairs, enu, freq_hz, weights, used, lat_rad, power_enu):
    """:func:`sky_loss` of the templates of ``patterns`` (K, n_ant, pol), the largest over the polarisations.

    On :data:`LOSS_BASELINES` of the baselines ``used`` (bool (bl,); ``pairs`` (bl, 2) into ``enu`` (n_ant, 3)
    metres), weighted by ``weights`` (bl, pol), at ``freq_hz``, over the tracks of :func:`sidereal_tracks` at
    latitude ``lat_rad`` (:data:`TRACK_POINTS`), each direction weighed by ``power_enu(directions, freq_hz)``
    (the beam's power response; one for both polarisations). 0 where no baseline is used.
    """
    idx = np.flatnonzero(used)
    if idx.size == 0:
        return 0.0
    idx = idx[np.round(np.linspace(0, idx.size - 1, min(idx.size, LOSS_BASELINES))).astype(int)]
    b = (enu[pairs[idx, 1]] - enu[pairs[idx, 0]]) * freq_hz / SPEED_OF_LIGHT
    B = template_basis(patterns, pairs[idx])  # (K^2, bl, pol)
    _, dirs = sidereal_tracks(lat_rad, *TRACK_POINTS)
    power = power_enu(dirs, freq_hz)
    loss = direction_loss(B, b, weights[idx], dirs.reshape(-1, 3)).reshape(-1, *dirs.shape[:2])  # (pol, dec, hour)
    return max(sky_loss(lp, power) for lp in loss)


def mean_amplitudes(amplitudes):
    """Each template's amplitude averaged over the integrations it was fitted on (time, K^2[, pol]) -> (K^2[,
    pol]): per polarisation, an integration whose amplitudes are all zero (no data there, :func:`fit_amplitudes`
    leaves them 0) is left out."""
    a = np.asarray(amplitudes)
    fitted = np.any(a != 0, axis=1, keepdims=True)  # (time, 1[, pol])
    n = fitted.sum(0)
    return np.where(n > 0, (a * fitted).sum(0) / np.maximum(n, 1), 0).astype(a.dtype)
