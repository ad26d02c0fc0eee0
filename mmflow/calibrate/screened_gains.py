"""Direction-independent gains against a model whose brightest sources the ionosphere moves and
scales (``calibrate.screen_sources``).

At 40-80 MHz the ionosphere refracts Cyg A and Cas A by up to tens of arcmin and scintillates
their flux by tens of percent from one integration to the next (paper section 3.4). Gains solved
against their *catalogue* models (:func:`mmflow.calibrate.stefcal.solve_gains`) absorb that
mismatch as antenna-based errors: errors a per-antenna DD solution can repair in the bright
sources' direction, but a physically constrained one (:mod:`mmflow.calibrate.dd_screen`, which
keeps the unmodelled sky) cannot. Here the gains are solved against the model the ionosphere
makes::

    V_ij(t) = g_i conj(g_j) [ sum_u M^u_ij(t) + sum_s a_s(t) e_si(t) conj(e_sj(t)) M^s_ij(t) ]
    e_si = exp(i B_si . theta_s(t))                                    (dd_screen's screen)

``u`` the unscreened sources, ``s`` the screened ones with a refractive offset ``theta_s(t)`` and
a flux factor ``a_s(t)`` per integration and polarisation. Alternating least squares, ``rounds``
times:

1. the gains ``g`` of the interval against the current model (Stefcal, outliers flagged);
2. per screened source and integration, ``theta_s`` and ``a_s`` fitted
   (:func:`mmflow.calibrate.dd_screen.solve_screen`) to ``X = V - G (M - M^s) G^H`` against
   ``G M^s G^H`` (``G = diag(g)``, the other sources at their current screens); then
   ``a_s(t) <- a_s(t) / <a>``, ``<a> = sum_st P_st a_st / sum_st P_st`` (``P_st`` the source's
   model power ``<G M^s G^H, G M^s G^H>_w``, one factor per polarisation): scintillation moves
   a source's flux between integrations with mean 1 (``exp(sigma z - sigma^2 / 2)``), so the
   screened sources' mean flux over the interval, and with it the flux scale, stays the
   catalogue's (Baars et al. 1977 for Cyg A). One common factor, not one per source: the data
   set each source's flux relative to the others (they are in different directions), and only
   the overall scale, which the gains' amplitude trades against where the screened sources
   dominate the sky, is set by this mean (per source it would impose the finite sample's mean
   scintillation, ~sigma / sqrt(n_int) = 4 % over 21 integrations, as a direction-dependent
   flux error). With ``reference`` only those sources' mean is 1 (the paper's recipe: Cyg A on
   the Baars scale) and the others' mean factor is their flux measured against the catalogue's
   (Cas A, which fades by ~0.8 %/yr).

With no screened source (or ``rounds=0``) the result is :func:`solve_gains` against the sum of
the catalogue models, unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmflow.calibrate.baselines import check_pairs, solution_matrices
from mmflow.calibrate.dd_screen import screen_gains, screen_normal_matrix, solve_screen
from mmflow.calibrate.stefcal import GainSolution, gains_per_integration, solve_gains
from mmflow.simulate.corrupt import gain_products


@dataclass
class ScreenedGains:
    """Result of :func:`solve_gains_screened`.

    solution: the gains (:class:`mmflow.calibrate.stefcal.GainSolution`) of the last round;
    offsets: (n_src, time, pol, 2) refractive offsets (rad; NaN for unscreened sources and where
    the source gave no model power); amplitude: (n_src, time, pol) flux factors (1 unscreened);
    flux: (n_src, pol) each screened source's flux over its catalogue model in the interval, the
    model-power-weighted mean of its factors (1 for the sources that set the scale on average;
    the measurement for the others; 1 unscreened, NaN where never fitted); unexplained: (pol,) the
    fraction of the data's power the calibrated model leaves (:func:`unexplained_fraction`).
    """

    solution: GainSolution
    offsets: np.ndarray
    amplitude: np.ndarray
    flux: np.ndarray
    unexplained: np.ndarray


def unexplained_fraction(vis, model, weights, pairs, solution, baseline_keep=None, batch=16):
    """Per polarisation, the fraction of the data's power that the calibrated model leaves::

        u_p = sum_tij w |V_ijp - g_ip conj(g_jp) M_ijp|^2 / sum_tij w |V_ijp|^2

    over the cross-correlations used (``baseline_keep``) of antennas not flagged. Near 0 where the
    model explains the data (the gains' errors from the unmodelled sky are then small); near 1 where
    the sources are down. NaN: no data. Computed ``batch`` integrations at a time."""
    pairs = np.asarray(pairs)
    g, fl = gains_per_integration(solution, vis.shape[0])
    g = np.where(fl, 0, np.nan_to_num(g))  # (time, n_ant, pol)
    drop = pairs[:, 0] == pairs[:, 1]
    if baseline_keep is not None:
        drop |= ~np.asarray(baseline_keep, bool)
    resid = total = 0.0
    for t0 in range(0, vis.shape[0], batch):  # a few integrations at a time: no copy of the interval's data
        t = slice(t0, t0 + batch)
        v = vis[t]
        w = np.where(drop[:, None], 0.0, np.broadcast_to(weights, vis.shape)[t])
        gp = gain_products(g[t], pairs)  # (batch, bl, pol)
        w = np.where((gp != 0) & (w > 0), w, 0.0)
        v = np.where(w > 0, v, 0)
        resid = resid + np.sum(w * np.abs(v - gp * np.broadcast_to(model, vis.shape)[t]) ** 2, (0, 1))
        total = total + np.sum(w * np.abs(v) ** 2, (0, 1))
    return np.where(total > 0, resid / np.where(total > 0, total, 1.0), np.nan)


def sum_of_sources(coherencies, which, rows=slice(None)):
    """``sum_{s in which} coherencies[s, rows]``, one source at a time in the order of ``sum(0)`` (the same
    bits): ``coherencies[which].sum(0)`` would first copy every selected source's model, at 256 antennas
    and a 30-min interval 1 GB beside the interval's 1.6 GB of models (the calibrate task's peak).

    ``coherencies`` (n_src, time, ...); ``which`` (n_src,) bool. Returns the sum (time[rows], ...), zeros
    when no source is selected.
    """
    idx = np.flatnonzero(which)
    if not len(idx):
        return np.zeros_like(coherencies[0, rows])
    out = np.array(coherencies[idx[0], rows])
    for s in idx[1:]:
        out += coherencies[s, rows]
    return out


def screened_model(coherencies, basis, offsets, amplitude, screened, pairs):
    """``sum_u M^u_ij + sum_s a_s e_si conj(e_sj) M^s_ij``: (time, bl, pol) model visibilities.

    ``coherencies`` (n_src, time, bl, 1 or pol); ``basis`` (n_src, time, n_ant, 2)
    (:func:`mmflow.calibrate.dd_screen.screen_basis`); ``offsets`` (n_src, time, pol, 2) and
    ``amplitude`` (n_src, time, pol) of the ``screened`` (n_src,) sources (NaN offsets: none).
    """
    rest = sum_of_sources(coherencies, ~screened)
    model = np.array(np.broadcast_to(rest, rest.shape[:-1] + (offsets.shape[2],)), complex)
    for s in np.flatnonzero(screened):
        h = screen_gains(basis[s][:, None], np.nan_to_num(offsets[s]), amplitude[s])  # (time, pol, n_ant)
        model += gain_products(np.moveaxis(h, 1, 2), pairs) * coherencies[s]
    return model


def solve_gains_screened(vis, coherencies, weights, pairs, n_ant, basis, screened, *, reference=None, rounds=2,
                         batch=16, screen_tol=1e-4, screen_max_iter=30, baseline_keep=None, threads=None, **solve_kw):
    """Gains of one solution set against the catalogue model with the screened sources refracted
    and scintillating (module docstring).

    Parameters
    ----------
    vis : ndarray (time, bl, pol); weights broadcastable to it (0 = flagged)
    coherencies : ndarray (n_src, time, bl) or (n_src, time, bl, pol): each source's catalogue model
        through the beam, one for every polarisation or one per polarisation (each feed's own power
        beam: :func:`mmflow.telescope.jones.feed_telescopes`)
    pairs : ndarray (n_bl, 2); n_ant : int
    basis : ndarray (n_src, time, n_ant, 2): phase per unit offset
        (:func:`mmflow.calibrate.dd_screen.screen_basis`); read for the screened sources only
    screened : bool array (n_src,): the sources given an offset and a flux factor per integration
    reference : bool array (n_src,), optional
        Of the screened sources, those whose catalogue flux sets the scale (their factors' mean is
        1); the other screened sources' flux is measured (``flux``). Default: every screened one.
        Where none of them gives model power, every screened source sets it.
    rounds : int
        Alternations of gains and screens (0: plain :func:`solve_gains`).
    batch : int
        Integrations whose screens are fitted together (memory ~ batch x n_pol x n_ant^2).
    screen_tol, screen_max_iter : the screen fit's convergence (largest antenna phase step, rad)
    baseline_keep : bool (n_bl,), optional: baselines used (the gains' and the screens')
    **solve_kw : passed to :func:`solve_gains` (solint, tol, max_iter, damping, outlier_sigma, ...)

    Returns
    -------
    ScreenedGains
    """
    vis = np.asarray(vis)
    T, B, P = vis.shape
    pairs = check_pairs(pairs, n_ant)
    coherencies = np.asarray(coherencies)
    if coherencies.ndim == 3:  # one model for every polarisation
        coherencies = coherencies[..., None]
    screened = np.asarray(screened, bool)
    n_src = coherencies.shape[0]
    offsets = np.full((n_src, T, P, 2), np.nan)
    amplitude = np.ones((n_src, T, P))
    reference = screened if reference is None else np.asarray(reference, bool) & screened
    kw = dict(baseline_keep=baseline_keep, threads=threads, **solve_kw)
    model = coherencies.sum(0)
    sol = solve_gains(vis, model, weights, pairs, n_ant, **kw)
    if not screened.any() or rounds <= 0:
        return ScreenedGains(sol, offsets, amplitude, np.ones((n_src, P)),
                             unexplained_fraction(vis, model, weights, pairs, sol, baseline_keep))
    w = np.array(np.broadcast_to(weights, vis.shape), float)
    w[:, pairs[:, 0] == pairs[:, 1]] = 0.0
    if baseline_keep is not None:
        w[:, ~np.asarray(baseline_keep, bool)] = 0.0
    v = np.where(w > 0, vis, 0)
    th = np.zeros((n_src, T * P, 2))
    for _ in range(rounds):
        g, fl = gains_per_integration(sol, T)  # (time, n_ant, pol)
        g = np.where(fl, 0, g)
        power = _fit_screens(v, w, coherencies, pairs, n_ant, basis, screened, g, th, amplitude, batch, screen_tol,
                             screen_max_iter, threads)
        fitted = screened[:, None, None] & (amplitude > 0)
        offsets[:] = np.where(fitted[..., None], th.reshape(n_src, T, P, 2), np.nan)
        # scintillation moves flux between integrations with mean 1: the screened sources' mean flux
        # over the interval, weighted by their model power, stays the catalogue's (one factor per pol)
        wp = np.where(fitted, power, 0.0)
        ref = wp * reference[:, None, None]
        ref = np.where(ref.sum((0, 1)) > 0, ref, wp)  # no reference source up: every screened one
        mean = np.sum(ref * amplitude, (0, 1)) / np.where(ref.sum((0, 1)) > 0, ref.sum((0, 1)), 1.0)  # (pol,)
        amplitude[:] = np.where(fitted, amplitude / np.where(mean > 0, mean, 1.0), 1.0)
        seen = wp.sum(1) > 0  # (n_src, pol)
        flux = np.where(screened[:, None], np.where(seen, np.sum(wp * amplitude, 1) / np.where(seen, wp.sum(1), 1.0),
                                                     np.nan), 1.0)
        model = screened_model(coherencies, basis, offsets, amplitude, screened, pairs)
        sol = solve_gains(vis, model, weights, pairs, n_ant, g0=sol.gains, **kw)
    return ScreenedGains(sol, offsets, amplitude, flux, unexplained_fraction(vis, model, weights, pairs, sol,
                                                                             baseline_keep))


def _fit_screens(v, w, coherencies, pairs, n_ant, basis, screened, g, th, amplitude, batch, tol, max_iter, threads):
    """One pass of the screen fits over all integrations, in batches (``th`` (n_src, T * P, 2) and
    ``amplitude`` (n_src, T, P) updated in place; ``g`` (T, n_ant, P) the current gains). Returns
    each screened source's model power ``<G M G^H, G M G^H>_w`` (n_src, T, P)."""
    T, B, P = v.shape
    n_src = coherencies.shape[0]
    power = np.zeros((n_src, T, P))
    scr = np.flatnonzero(screened)
    for t0 in range(0, T, batch):
        t1 = min(T, t0 + batch)
        nb = t1 - t0
        rows = slice(t0 * P, t1 * P)
        gp = gain_products(g[t0:t1], pairs)  # (nb, bl, P)
        W = solution_matrices(w[t0:t1], pairs, n_ant)  # solution s = t * P + p
        amp = np.moveaxis(amplitude[:, t0:t1], -1, 2).reshape(n_src, nb * P)  # (n_src, nb * P)
        Ms = {s: solution_matrices(gp * coherencies[s, t0:t1], pairs, n_ant) for s in scr}
        bs = {s: np.repeat(basis[s, t0:t1], P, axis=0) for s in scr}
        rest = sum_of_sources(coherencies, ~screened, slice(t0, t1))  # (nb, bl, 1 or P): the unscreened
        X = solution_matrices(v[t0:t1] - gp * rest, pairs, n_ant)

        def screened_part(s):
            e = np.exp(1j * np.einsum("sak,sk->sa", bs[s], th[s, rows]))
            return amp[s][:, None, None] * e[:, :, None] * np.conj(e[:, None, :]) * Ms[s]

        for s in scr:
            Xs = X - sum(screened_part(r) for r in scr if r != s)
            a = np.ones(nb * P)
            normal = screen_normal_matrix(Ms[s], W, bs[s])  # its second part: the model power
            active = normal[1] > 0
            solve_screen(Xs, Ms[s], W, bs[s], active, th[s, rows], a, tol=tol, max_iter=max_iter,
                         normal=normal, threads=threads)
            amp[s] = np.where(active, a, 0.0)
            amplitude[s, t0:t1] = amp[s].reshape(nb, P)
            power[s, t0:t1] = normal[1].reshape(nb, P)
    return power
