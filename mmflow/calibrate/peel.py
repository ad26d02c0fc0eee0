"""Peeling: per-integration direction-dependent (DD) gains of bright sources, and subtraction.

Model of one integration (one pol), Hermitian antenna matrices::

    V = sum_{s peeled} G_s M_s G_s^H + sum_{s subtracted or modelled} a_s M_s + R

``M_s`` is the source's model coherency (:mod:`mmflow.calibrate.coherency`), ``G_s =
diag(g_s)`` its DD gains and ``a_s`` a real fitted flux scale. Two models of the DD gains
(``peel(dd_model=...)``, the stage's ``peel.dd_model``):

* ``screen`` (default): ``g_si = sqrt(A_s) exp(i B_si . theta_s)`` with ``B_si = -2 pi x_i .
  (t_e, t_n) / lambda``: a refractive offset ``theta_s`` (2 real parameters: the ionosphere
  moves the source, a phase gradient across the array) and a scintillation amplitude ``A_s``
  (1 real parameter, the same for every antenna), solved by Gauss-Newton
  (:mod:`mmflow.calibrate.dd_screen`). This is the ionosphere's first-order effect on a compact
  array (paper section 3.4: refraction and scintillation), and with 3 parameters instead of
  ``2 N - 1`` the fit leaves the unmodelled sky in the data: on 40 antennas within 70 m at
  50 MHz, peeling Cyg A and Cas A keeps 98.4-99.7 % of a 100 Jy source 27-33 deg from Cyg A,
  against 75-87 % with per-antenna gains (``tests/unit/calibrate/test_peel_unmodelled.py``).
* ``antenna``: a free complex gain per antenna (Stefcal), as TTCal's ``peel``; for phase
  structure that is not a gradient (an array larger than the ionospheric patch).

A *modelled* source (``MODEL``) is fitted like a subtracted
one, so that its flux does not bias the DD gains and fluxes of the others, and is put back at
the end: it stays in the data (fainter catalogue sources that are imaged, not removed). The
algorithm (after TTCal's ``peel``, plus the modelled sources; paper section 3.5):

1. start ``g_s`` at 1 (or warm-start from the previous integration: gains or offsets) and ``a_s`` at 1;
   subtract every source: ``R = V - sum_s C_s``;
2. for ``passes`` passes: for each peeled source in decreasing flux order, put it back
   (``R += C_s``), re-solve its gains against ``R`` (the screen's offset and amplitude, or
   Stefcal, :func:`stefcal`, ``K = 1``) and subtract it again; then put every subtracted and
   modelled source back, solve their scales jointly by least squares (:func:`fit_scales`) and
   subtract them again;
3. guard: with the point-source estimator ``S(X) = Re sum w X conj(F) / sum w``,
   ``F = M / |M|`` (the source's fringe), a peeled source whose removed component has
   ``S(C_s) < guard * S(R + C_s)`` (default guard 0.9: peeling removed less than 90 % of
   the measured flux, e.g. a wrong model) is put back and subtracted with a fitted scale, and
   then every subtracted and modelled source's scale is refitted jointly (they were fitted
   beside DD gains that absorbed part of them);
4. the modelled sources are put back: ``R += a_s M_s``.

All integrations of a batch are solved together (independent solutions, vectorised); the
kernels are numba, split over antenna rows on :func:`mmflow.threads.n_threads` threads.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from mmflow.calibrate.baselines import check_pairs, from_matrix, solution_matrices, to_matrix
from mmflow.calibrate.dd_screen import screen_gains, screen_normal_matrix, solve_screen
from mmflow.calibrate.scale_fit import fit_scales, scale_system
from mmflow.calibrate.stefcal import run_rows, stefcal
from mmflow.errors import InputError

SKIP, PEEL, SUBTRACT, MODEL = 0, 1, 2, 3


@numba.njit(nogil=True, cache=True, fastmath=True)
def _add_component(R, M, g, scale, j0, j1):
    """``R[s, j, i] += scale[s] g[s, j] M[s, j, i] conj(g[s, i])`` for rows j0..j1 (scale 0: skip)."""
    S, N = R.shape[0], R.shape[1]
    for s in range(S):
        a = scale[s]
        if a == 0.0:
            continue
        for j in range(j0, j1):
            gjr = g[s, j].real * a
            gji = g[s, j].imag * a
            for i in range(N):
                mr = M[s, j, i].real
                mi = M[s, j, i].imag
                # (gj m) conj(gi)
                pr = gjr * mr - gji * mi
                pi = gjr * mi + gji * mr
                gr = g[s, i].real
                gim = g[s, i].imag
                R[s, j, i] += complex(pr * gr + pi * gim, pi * gr - pr * gim)


@numba.njit(nogil=True, cache=True)
def _inner(X, M, W, num, den, fnum, j0, j1):
    """Per row: ``num = sum w conj(M) X``, ``den = sum w |M|^2``, ``fnum = sum w X conj(M)/|M|``."""
    S, N = X.shape[0], X.shape[1]
    for s in range(S):
        for j in range(j0, j1):
            a = 0.0j
            d = 0.0
            f = 0.0j
            for i in range(N):
                w = W[s, j, i]
                if w == 0.0 or i == j:
                    continue
                m = M[s, j, i]
                am = abs(m)
                x = X[s, j, i]
                a += w * np.conj(m) * x
                d += w * am * am
                if am > 0.0:
                    f += w * x * np.conj(m) / am
            num[s, j] = a
            den[s, j] = d
            fnum[s, j] = f


@numba.njit(nogil=True, cache=True, fastmath=True)
def _guard_sums(R, M, W, g, fr, fc, j0, j1):
    """Per row: ``fr = sum w Re(R conj(M)/|M|)``, ``fc = sum w |M| Re(g_j conj(g_i))`` (= S(C) sum w)."""
    S, N = R.shape[0], R.shape[1]
    for s in range(S):
        for j in range(j0, j1):
            a = 0.0
            c = 0.0
            gjr = g[s, j].real
            gji = g[s, j].imag
            for i in range(N):
                w = W[s, j, i]
                if w == 0.0 or i == j:
                    continue
                m = M[s, j, i]
                am = abs(m)
                if am == 0.0:
                    continue
                x = R[s, j, i]
                a += w * (x.real * m.real + x.imag * m.imag) / am
                c += w * am * (gjr * g[s, i].real + gji * g[s, i].imag)
            fr[s, j] = a
            fc[s, j] = c


def guard_fluxes(R, M, W, g, threads=None):
    """``(S(R) sum w, S(G M G^H) sum w)`` per solution without forming the component."""
    S, N = R.shape[0], R.shape[1]
    fr, fc = np.zeros((S, N)), np.zeros((S, N))
    run_rows(_guard_sums, N, (R, M, W, np.ascontiguousarray(g, np.complex128), fr, fc), threads)
    return fr.sum(1), fc.sum(1)


def add_component(R, M, g, scale, threads=None):
    """In place: ``R += scale G M G^H`` (S, N, N); ``scale`` (S,) real, 0 skips a solution."""
    run_rows(_add_component, R.shape[1], (R, M, g, np.asarray(scale, float)), threads)


def projections(X, M, W, threads=None):
    """``(Re<M, X>_w, <M, M>_w, S(X) * sum w)`` per solution (S,), summed over all baselines."""
    S, N = X.shape[0], X.shape[1]
    num = np.zeros((S, N), complex)
    den = np.zeros((S, N))
    fnum = np.zeros((S, N), complex)
    run_rows(_inner, N, (X, M, W, num, den, fnum), threads)
    return num.sum(1).real, den.sum(1), fnum.sum(1).real


@dataclass
class PeelResult:
    """One batch of independent solutions (S = integrations x pols), n_src sources.

    dd_gains (n_src, S, N); scale (n_src, S) fitted flux scale (1 for peeled); mode (n_src, S)
    as used at the end (SKIP/PEEL/SUBTRACT/MODEL); guard (n_src, S) True where the guard turned a
    peel into a subtraction; measured, removed (n_src, S) the guard's estimator S(.) of the
    source in the data and of what peeling removed; iterations (n_src, S) Stefcal iterations
    summed over passes; converged (n_src, S) in the last pass; residual (S, N, N); offsets
    (n_src, S, 2) the screen model's refractive offsets (rad; NaN with per-antenna DD gains).
    """

    dd_gains: np.ndarray
    scale: np.ndarray
    mode: np.ndarray
    guard: np.ndarray
    measured: np.ndarray
    removed: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    residual: np.ndarray
    offsets: np.ndarray


def solution_intervals(n_time, n_pol, solint):
    """Solution indices ``t * n_pol + p`` of each DD solution interval, grouped by interval length.

    Interval ``k`` holds integrations ``k solint .. (k + 1) solint - 1`` of one polarisation (the
    last one may be shorter). Returns a list of int arrays (n_intervals, K), one per distinct K.
    """
    groups = {}
    for t0 in range(0, n_time, solint):
        ts = np.arange(t0, min(n_time, t0 + solint))
        for p in range(n_pol):
            groups.setdefault(len(ts), []).append(ts * n_pol + p)
    return [np.array(v) for _, v in sorted(groups.items())]


def _solve_interval_gains(R, M, W, peel, p, amp, intervals, tol, max_iter, damping, threads):
    """DD gains ``h(t) = sqrt(a(t)) p`` of one source, ``p`` shared by the integrations of each
    interval (refraction: a phase screen smooth over the interval) and ``a(t) >= 0`` per
    integration (scintillation), with the source put back in ``R`` (S, N, N).

    ``p`` by Stefcal summed over the interval's integrations against the model ``a(t) M(t)``,
    then ``a(t) = Re<P M P^H, R>_w / <P M P^H, P M P^H>_w`` per integration. Updates ``p`` and
    ``amp`` (S, N), (S,) in place for the solutions with ``peel``; returns Stefcal's
    (iterations, converged) per solution.
    """
    S = R.shape[0]
    iters = np.zeros(S, int)
    conv = np.ones(S, bool)
    for idx in intervals:
        act = peel[idx]  # (G, K)
        use = act.any(1)
        if not use.any():
            continue
        Wk = W[idx] * act[..., None, None]
        Mk = M[idx] * amp[idx][..., None, None]
        g0 = p[idx[:, 0]]
        res = stefcal(R[idx], Mk, Wk, g0, tol=tol, max_iter=max_iter, damping=damping, ref_ant=-1,
                      threads=threads, diagnostics=False, active=use)
        for k in range(idx.shape[1]):
            sel = act[:, k]
            p[idx[sel, k]] = res.gains[sel]
            iters[idx[sel, k]] = res.iterations[sel]
            conv[idx[sel, k]] = res.converged[sel]
    Mp = M * (p[:, :, None] * np.conj(p[:, None, :]))
    num, den, _ = projections(R, Mp, W, threads)
    new = np.where(den > 0, np.maximum(num, 0.0) / np.maximum(den, 1e-300), 0.0)
    amp[peel] = new[peel]
    return iters, conv


def _interval_groups(intervals, S):
    """Group id per solution (S,) of :func:`solution_intervals`'s intervals (None: each its own)."""
    groups = np.arange(S)
    for idx in intervals or ():
        groups[idx] = idx[:, :1]
    return groups


def peel_dense(V, coherencies, W, modes, g0=None, *, passes=3, tol=1e-4, max_iter=30, guard=0.9,
               damping="half", threads=None, intervals=None, screen_basis=None, offsets0=None):
    """Peel and subtract sources from S independent antenna-matrix visibilities.

    Parameters
    ----------
    V : ndarray (S, N, N) complex, Hermitian and finite; not modified
    coherencies : ndarray (n_src, S, N, N) complex: model coherencies M_s (Jy)
    W : ndarray (S, N, N) real: solve weights (0 = unused; autos and short baselines should be 0).
        Subtraction acts on every baseline whatever its weight.
    modes : int array (n_src, S): SKIP, PEEL, SUBTRACT or MODEL per source and solution
    g0 : ndarray (n_src, S, N), optional warm start for the DD gains
    passes, tol, max_iter, damping : outer passes; Stefcal tolerance, iterations, damping
    guard : float or None: the fraction of the measured flux peeling must remove
    intervals : list of int arrays (n_interval, K), optional (:func:`solution_intervals`)
        DD solution intervals: the peeled sources' gains are ``sqrt(a_s(t)) p_s`` with ``p_s``
        shared by the solutions of an interval and a real amplitude ``a_s(t)`` per solution
        (:func:`_solve_interval_gains`). Default: every solution its own gains (K = 1).
    screen_basis : ndarray (n_src, S, N, 2), optional: the peeled sources' DD gains constrained to
        a refractive offset and an amplitude per solution, ``h = sqrt(a) exp(i B theta)``
        (:mod:`mmflow.calibrate.dd_screen`; with ``intervals`` the offset is shared over each
        interval, the amplitude per solution). Default: per-antenna DD gains (Stefcal).
    offsets0 : ndarray (n_src, S, 2), optional: start of the screen offsets (rad; default 0).
        ``g0`` is for per-antenna DD gains only.

    Returns
    -------
    PeelResult
    """
    n_src, S, N = coherencies.shape[:3]
    modes = np.array(np.broadcast_to(modes, (n_src, S)), np.int8)
    screen = screen_basis is not None
    if screen and g0 is not None:
        raise ValueError("peel_dense: g0 starts per-antenna DD gains; start the screen model with offsets0")
    g = np.ones((n_src, S, N), np.complex128) if g0 is None else np.array(g0, np.complex128, copy=True)
    offsets = np.full((n_src, S, 2), np.nan)
    if screen:
        offsets = (
            np.zeros((n_src, S, 2)) if offsets0 is None else np.nan_to_num(np.broadcast_to(offsets0, (n_src, S, 2)))
        )
        g = screen_gains(screen_basis, offsets, np.ones((n_src, S)))
        screen_amp = np.ones((n_src, S))
        groups = _interval_groups(intervals, S)
        normal = {}
    scale = np.ones((n_src, S))
    iters = np.zeros((n_src, S), int)
    conv = np.ones((n_src, S), bool)
    R = np.array(V, np.result_type(V.dtype, np.complex64), copy=True)
    power = np.array([np.abs(coherencies[s]).sum() for s in range(n_src)])
    order = np.argsort(-power, kind="stable")
    # 1. subtract everything with the starting gains
    for s in order:
        add_component(R, coherencies[s], g[s], -scale[s] * (modes[s] != SKIP), threads)
    if intervals is not None and not screen:  # interval gains p and amplitudes a with g = sqrt(a) p
        p_int = g.copy()
        amp = np.ones((n_src, S))
    # 2. passes (the scaled sources' normal equations are the same in every pass)
    scaled = (modes == SUBTRACT) | (modes == MODEL)
    system = scale_system(coherencies, W, scaled, R.dtype)
    for _ in range(passes):
        for s in order:
            peel = modes[s] == PEEL
            if peel.any() and screen:
                add_component(R, coherencies[s], g[s], 1.0 * peel, threads)
                if s not in normal:  # the normal matrix depends on the model and weights only
                    normal[s] = screen_normal_matrix(coherencies[s], W, screen_basis[s])
                it, cv = solve_screen(R, coherencies[s], W, screen_basis[s], peel, offsets[s], screen_amp[s], groups,
                                      tol=tol, max_iter=max_iter, normal=normal[s], threads=threads)
                g[s, peel] = screen_gains(screen_basis[s], offsets[s], screen_amp[s])[peel]
                iters[s, peel] += it[peel]
                conv[s, peel] = cv[peel]
                add_component(R, coherencies[s], g[s], -1.0 * peel, threads)
            elif peel.any() and intervals is not None:
                add_component(R, coherencies[s], g[s], 1.0 * peel, threads)
                it, cv = _solve_interval_gains(R, coherencies[s], W, peel, p_int[s], amp[s], intervals, tol,
                                               max_iter, damping, threads)
                g[s, peel] = (np.sqrt(amp[s])[:, None] * p_int[s])[peel]
                iters[s, peel] += it[peel]
                conv[s, peel] = cv[peel]
                add_component(R, coherencies[s], g[s], -1.0 * peel, threads)
            elif peel.any():
                add_component(R, coherencies[s], g[s], 1.0 * peel, threads)
                res = stefcal(R[:, None], coherencies[s][:, None], W[:, None], g[s], tol=tol, max_iter=max_iter,
                              damping=damping, ref_ant=-1, threads=threads, diagnostics=False, active=peel)
                g[s, peel] = res.gains[peel]
                iters[s, peel] += res.iterations[peel]
                conv[s, peel] = res.converged[peel]
                add_component(R, coherencies[s], g[s], -1.0 * peel, threads)
        fit_scales(R, coherencies, W, scale, scaled, system=system)
    del system  # the scaled sources' models as rows (a copy where they are not contiguous)
    # 3. guard
    measured = np.zeros((n_src, S))
    removed = np.zeros((n_src, S))
    fired = np.zeros((n_src, S), bool)
    wsum = W.reshape(S, -1).sum(1) - np.einsum("sii->s", W)
    for s in order:
        peel = modes[s] == PEEL
        if not peel.any():
            continue
        f_resid, f_removed = guard_fluxes(R, coherencies[s], W, g[s], threads)
        f_measured = f_resid + f_removed
        used = peel & (wsum > 0)  # an integration without usable baselines measures nothing
        measured[s] = np.where(used, f_measured / np.where(used, wsum, 1.0), 0)
        removed[s] = np.where(used, f_removed / np.where(used, wsum, 1.0), 0)
        if guard is not None:
            fired[s] = peel & ((removed[s] < guard * measured[s]) | (measured[s] <= 0))
        if fired[s].any():
            add_component(R, coherencies[s], g[s], 1.0 * fired[s], threads)
            modes[s][fired[s]] = SUBTRACT
            scale[s][fired[s]] = 0.0
            only = np.zeros((n_src, S), bool)
            only[s] = fired[s]
            fit_scales(R, coherencies, W, scale, only)  # before the next source's guard reads R
    if fired.any():  # the others' scales were fitted beside DD gains that are gone now: refit them all
        fit_scales(R, coherencies, W, scale, (modes == SUBTRACT) | (modes == MODEL))
    # 4. the modelled sources back into the residual, with the scale fitted jointly with the others
    for s in order:
        held = modes[s] == MODEL
        if held.any():
            add_component(R, coherencies[s], np.ones(R.shape[:2], complex), scale[s] * held, threads)
    scale[modes == PEEL] = 1.0
    scale[modes == SKIP] = 0.0
    offsets[modes != PEEL] = np.nan
    return PeelResult(g, scale, modes, fired, measured, removed, iters, conv, R, offsets)


def select_modes(apparent_flux, elevation, *, peelable, peel_min_elevation_deg=10.0, peel_min_flux_jy=0.0,
                 subtract_min_flux_jy=0.0, modelled=None):
    """Per source and integration: PEEL, SUBTRACT, MODEL or SKIP.

    Parameters
    ----------
    apparent_flux, elevation : ndarray (n_src, n_time): published flux x beam (Jy), elevation (rad)
    peelable : bool array (n_src,): sources that may be peeled (e.g. Cyg A, Cas A, Vir A, Tau A)
    peel_min_elevation_deg, peel_min_flux_jy : scalars or (n_src,) arrays: peel only above both
        (e.g. 10 deg for Cyg A/Cas A, higher for Vir A/Tau A: "peeled when high")
    subtract_min_flux_jy : below this apparent flux a source is skipped
    modelled : bool array (n_src,), optional: sources only modelled (fitted, then left in the data)

    A source below the horizon is skipped; a modelled source above it is MODEL; a peelable
    source outside its peel limits, or a source that is not peelable, is subtracted (fitted flux).
    """
    el_min = np.deg2rad(np.asarray(peel_min_elevation_deg, float))
    el_min = el_min[:, None] if el_min.ndim else el_min
    f_min = np.asarray(peel_min_flux_jy, float)
    f_min = f_min[:, None] if f_min.ndim else f_min
    up = (elevation > 0) & (apparent_flux > subtract_min_flux_jy)
    peel = up & np.asarray(peelable, bool)[:, None] & (elevation >= el_min) & (apparent_flux >= f_min)
    held = np.zeros(len(peel), bool) if modelled is None else np.asarray(modelled, bool)
    peel &= ~held[:, None]
    kept = np.where(held[:, None], MODEL, SUBTRACT)
    return np.where(peel, PEEL, np.where(up, kept, SKIP)).astype(np.int8)


@dataclass
class PeelSolution(PeelResult):
    """Per-integration peeling products in baseline layout.

    dd_gains (n_src, time, n_ant, pol); scale, mode, guard, measured, removed, iterations,
    converged (n_src, time, pol); residual (time, bl, pol) (the peeled visibilities); offsets
    (n_src, time, pol, 2) the screen model's refractive offsets (rad; NaN for ``antenna``).
    The fields of :class:`PeelResult`, laid out per integration.
    """


DD_MODELS = ("screen", "antenna")


def peel(vis, weights, coherencies, pairs, n_ant, modes, *, dd_model: str = "screen",
         screen_basis: np.ndarray | None = None, baseline_keep: np.ndarray | None = None, batch: int = 16,
         warm_start: bool = False, g0: np.ndarray | None = None, threads: int | None = None, solint: int = 1,
         passes: int = 3, tol: float = 1e-4, max_iter: int = 30, guard: float | None = 0.9,
         damping: str = "half", dtype=np.complex128) -> PeelSolution:
    """Peel a time chunk in batches of ``batch`` integrations (memory bounded by the batch).

    The defaults are the schema's (``PeelConfig``).

    Parameters
    ----------
    vis : ndarray (time, bl, pol); weights broadcastable to it (0 = flagged)
    coherencies : ndarray (n_src, time, bl) or (n_src, time, bl, pol)
    modes : int array (n_src, time) from :func:`select_modes`
    dd_model : {"screen", "antenna"}
        The peeled sources' DD gains. ``screen``: a refractive offset (a phase gradient across
        the array) and a scintillation amplitude per source and solution, 3 real parameters
        (:mod:`mmflow.calibrate.dd_screen`); needs ``screen_basis``. ``antenna``: a free complex
        gain per antenna (Stefcal), ``2 N - 1`` parameters, which on a compact array also absorb
        part of the sky that is not modelled.
    screen_basis : ndarray (n_src, time, n_ant, 2): ``B_ik = -2 pi x_i . t_k / lambda``
        (:func:`mmflow.calibrate.dd_screen.screen_basis`), the same for every polarisation
    baseline_keep : bool (n_bl,), baselines used to solve (min length); autos never are
    warm_start : start each batch from the last integration of the previous batch (the gains,
        or the screen's offsets) instead of 1 (``batch=1``: every integration starts from the
        previous one)
    g0 : ndarray (n_src, n_ant, pol), optional: start of the first batch (``antenna`` only)
    solint : int, DD solution interval in integrations, counted from the chunk's first: the
        per-antenna gains (``antenna``) or the offset (``screen``) shared over the interval, the
        amplitude per integration; 1: every integration its own. ``batch`` is rounded up to a
        multiple of it.
    passes, tol, max_iter, guard, damping : :func:`peel_dense` (``tol``: Stefcal's relative gain
        change, or the screen's largest antenna phase change in rad)
    dtype : complex64 or complex128
        Working precision of the solve: each batch's antenna matrices (data, models, residual) are
        formed in it. complex64 halves the memory traffic that bounds peeling (``mmflow bench
        calibrate`` times it so); it resolves a ``tol`` down to ~1e-5 (the peel stage's ``SINGLE_PRECISION_TOL``).

    Returns
    -------
    PeelSolution
    """
    if dd_model not in DD_MODELS:
        raise ValueError(f"peel: dd_model must be one of {DD_MODELS}, not {dd_model!r}")
    screen = dd_model == "screen"
    vis = np.asarray(vis)
    T, B, P = vis.shape
    pairs = check_pairs(pairs, n_ant)
    n_src = coherencies.shape[0]
    if screen:
        if screen_basis is None:
            raise ValueError("peel: dd_model='screen' needs screen_basis (n_src, time, n_ant, 2)")
        if g0 is not None:
            raise ValueError("peel: g0 starts per-antenna DD gains (dd_model='antenna')")
        screen_basis = np.broadcast_to(screen_basis, (n_src, T, n_ant, 2))
    solint = max(1, int(solint))
    batch = -(-batch // solint) * solint
    coh = coherencies if coherencies.ndim == 4 else coherencies[..., None]
    w = np.array(np.broadcast_to(weights, vis.shape), float)
    bad = ~np.isfinite(vis)
    if np.any(bad & (w > 0)):
        raise InputError("visibilities", "data", "NaN or inf in unflagged data",
                         "flag those samples (weight 0) before peeling")
    if bad.any():
        vis = np.where(bad, 0, vis)  # flagged samples may hold anything; the kernels need finite numbers
    w[:, pairs[:, 0] == pairs[:, 1]] = 0.0
    if baseline_keep is not None:
        w[:, ~np.asarray(baseline_keep, bool)] = 0.0
    out = PeelSolution(np.ones((n_src, T, n_ant, P), complex), np.zeros((n_src, T, P)),
                       np.zeros((n_src, T, P), np.int8), np.zeros((n_src, T, P), bool),
                       np.zeros((n_src, T, P)), np.zeros((n_src, T, P)), np.zeros((n_src, T, P), int),
                       np.zeros((n_src, T, P), bool), np.zeros(vis.shape, vis.dtype),
                       np.full((n_src, T, P, 2), np.nan))
    # the start of the next batch, per source and pol: gains (n_src, P, N) or offsets (n_src, P, 2)
    last = None if g0 is None else np.moveaxis(np.asarray(g0, complex), -1, 1)
    buffers = {}  # a full batch's antenna matrices, reused: new ones each batch cost their page faults again
    for t0 in range(0, T, batch):
        t1 = min(T, t0 + batch)
        nb = t1 - t0

        def buffer(name, shape, dt):
            if nb < batch:  # the last, short batch
                return np.empty(shape, dt)
            return buffers.setdefault(name, np.empty(shape, dt))

        def dense(x, out=None):  # (nb, bl, P) -> (nb * P, N, N), solution index = t * P + p
            return solution_matrices(x, pairs, n_ant, out=out)

        def per_solution(x):  # (n_src, nb, ...) -> (n_src, nb * P, ...), the same for every pol
            return np.repeat(x, P, axis=1)

        V = dense(vis[t0:t1], out=buffer("V", (nb * P, n_ant, n_ant), dtype))
        W = dense(w[t0:t1].astype(np.float32), out=buffer("W", (nb * P, n_ant, n_ant), np.float32))
        M = buffer("M", (n_src, nb * P, n_ant, n_ant), dtype)  # filled in place: no stacked copy
        for s in range(n_src):
            if coh.shape[-1] == 1 and P > 1:  # one model for every polarisation: scattered once, copied
                to_matrix(coh[s, t0:t1, :, 0], pairs, n_ant, out=M[s, :nb])
                for k in range(nb * P - 1, 0, -1):  # solution t * P + p <- t, last first (k >= t: no overwrite)
                    M[s, k] = M[s, k // P]
            else:
                dense(np.broadcast_to(coh[s, t0:t1], (nb, B, P)), out=M[s])
        md = per_solution(np.asarray(modes)[:, t0:t1])
        start = None
        if last is not None:
            start = np.broadcast_to(last[:, None], (n_src, nb) + last.shape[1:])
            start = start.reshape((n_src, nb * P) + last.shape[2:])
        intervals = solution_intervals(nb, P, solint) if solint > 1 else None
        kw = dict(passes=passes, tol=tol, max_iter=max_iter, guard=guard, damping=damping, threads=threads,
                  intervals=intervals)
        if screen:
            r = peel_dense(V, M, W, md, screen_basis=per_solution(screen_basis[:, t0:t1]), offsets0=start, **kw)
        else:
            r = peel_dense(V, M, W, md, start, **kw)
        if warm_start:
            state = r.offsets if screen else r.dd_gains
            fin = state.reshape((n_src, nb, P) + state.shape[2:])[:, -1]
            ok = np.isfinite(fin).all(-1) & (screen or (np.abs(fin).min(-1) > 0))
            fallback = (0.0 if screen else 1.0) if last is None else last
            last = np.where(ok[..., None], fin, fallback)

        def back(x):  # (n_src, nb * P, ...) -> (n_src, nb, ..., P)
            x = x.reshape((n_src, nb, P) + x.shape[2:])
            return np.moveaxis(x, 2, -1)

        out.dd_gains[:, t0:t1] = back(r.dd_gains)
        for name in ("scale", "mode", "guard", "measured", "removed", "iterations", "converged"):
            getattr(out, name)[:, t0:t1] = back(getattr(r, name))
        out.offsets[:, t0:t1] = r.offsets.reshape(n_src, nb, P, 2)
        out.residual[t0:t1] = np.moveaxis(from_matrix(r.residual, pairs).reshape(nb, P, B), 1, -1)
    return out
