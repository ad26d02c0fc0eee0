"""Direction-dependent gains constrained by their physics: a refractive offset and a
scintillation amplitude per source and solution (``peel.dd_model: screen``).

A compact array sees a bright source through a patch of ionosphere much smaller than the
array's distance to it: to first order the ionosphere moves the source (refraction, a phase
gradient across the array) and scales its flux (amplitude scintillation, the same for every
antenna). The DD gains of peeled source ``s`` in one solution are then::

    h_i = sqrt(a) exp(i phi_i),   phi_i = sum_k B_ik theta_k,
    B_ik = -2 pi x_i . t_k / lambda                                   (k = 1, 2)

with ``x_i`` the antenna positions (ENU, m), ``t_1, t_2`` the sky's east and north unit vectors
at the source (in ENU), ``theta = (dl, dm)`` the refractive offset on the sky (rad) and ``a >= 0``
the flux factor: ``h_i conj(h_j) M_ij`` is the model moved by ``theta`` and scaled by ``a``
(the simulator's :func:`mmflow.simulate.corrupt.direction_dependent_gains`). Three real
parameters per source and solution instead of ``2 N_ant - 1``: per-antenna DD gains fitted on
``N (N - 1) / 2`` baselines absorb a fraction ~``(2 N - 1) / (N (N - 1))`` of any *unmodelled*
sky along with the source (14 % for two peeled sources on 40 antennas); the screen absorbs
~``3 / (N (N - 1))`` per source. What the screen cannot follow: phase structure across the array
that is not a gradient (an array larger than the ionospheric patch, e.g. km baselines, or
antenna-based errors left by the direction-independent calibration): use ``antenna`` there.

Least squares: minimise ``sum_ij w_ij |X_ij - a c_ij|^2`` with ``c_ij = e_i conj(e_j) M_ij``,
``e_i = exp(i phi_i)``, ``X`` the data with the source put back. For a given ``theta`` the
amplitude is linear, ``a = Re<c, X>_w / <c, c>_w``; for ``theta`` Gauss-Newton, whose normal
matrix does not depend on ``theta`` (``|c_ij| = |M_ij|``)::

    a^2 G dtheta = a b,   G_kl = sum_ij w_ij |M_ij|^2 (B_ik - B_jk)(B_il - B_jl),
                          b_k = sum_ij w_ij (B_ik - B_jk) Im(conj(c_ij) X_ij)

(sums over both triangles of the Hermitian matrices; with ``Q_ij = w_ij |M_ij|^2``,
``G = 2 B^T diag(Q 1) B - 2 B^T Q B`` and ``b = 2 B^T y``, ``y_i = sum_j w_ij Im(conj(c_ij) X_ij)``).
Solutions grouped in an interval share ``theta`` (the normal equations summed over the group,
each with its own ``a``); a step that lowers the group's fitted power
``sum_t Re<c, X>_w^2 / <c, c>_w`` is halved. Converged when the step moves no antenna's phase
by more than ``tol`` rad.
"""
from __future__ import annotations

import numba
import numpy as np

from mmflow.calibrate.stefcal import run_rows
from mmflow.conventions import SPEED_OF_LIGHT
from mmflow.sky.frames import source_enu, tangent_basis


def sky_tangents_enu(telescope, lsts, vec_date):
    """The sky's east and north unit vectors at each source, in ENU: (n_src, n_time, 2, 3).

    ``vec_date`` (n_src, 3) source directions in the frame of date; east and north of
    :func:`mmflow.sky.frames.tangent_basis`, turned to ENU at each sidereal angle ``lsts``.
    """
    e, n = tangent_basis(np.atleast_2d(vec_date))
    return np.stack([source_enu(telescope, lsts, e), source_enu(telescope, lsts, n)], axis=-2)


def screen_basis(enu_m, freq_hz, tangents_enu):
    """Phase per unit offset, ``B_ik = -2 pi x_i . t_k / lambda``: (..., n_ant, 2).

    ``enu_m`` (n_ant, 3) antenna positions (m); ``tangents_enu`` (..., 2, 3) two unit vectors
    perpendicular to the source (e.g. :func:`sky_tangents_enu`).
    """
    lam = SPEED_OF_LIGHT / float(freq_hz)
    return -2 * np.pi / lam * np.einsum("...kl,al->...ak", np.asarray(tangents_enu, float), np.asarray(enu_m, float))


def screen_gains(basis, offsets, amplitude):
    """``h_i = sqrt(a) exp(i B_i . theta)``: (..., n_ant) from basis (..., n_ant, 2), offsets (..., 2), a (...)."""
    phase = np.einsum("...ak,...k->...a", basis, offsets)
    return np.sqrt(np.maximum(amplitude, 0.0))[..., None] * np.exp(1j * phase)


@numba.njit(nogil=True, cache=True, fastmath=True)
def _screen_sums(X, M, W, e, active, out, j0, j1):
    """Per row ``j``: ``out[s, j] = sum_i w_ji conj(c_ji) X_ji`` with ``c_ji = e_j conj(e_i) M_ji``."""
    S, N = X.shape[0], X.shape[1]
    for s in range(S):
        if not active[s]:
            continue
        for j in range(j0, j1):
            acc = 0.0j
            for i in range(N):
                w = W[s, j, i]
                if w == 0.0 or i == j:
                    continue
                acc += w * np.conj(M[s, j, i]) * e[s, i] * X[s, j, i]
            out[s, j] = np.conj(e[s, j]) * acc


def screen_normal_matrix(M, W, basis):
    """``(G (S, 2, 2), <M, M>_w (S,))`` of the Gauss-Newton step (independent of the offsets)."""
    Q = (W * (M.real ** 2 + M.imag ** 2)).astype(float)  # |M|^2 in the models' precision: no float64 temporaries
    Q[:, np.arange(Q.shape[1]), np.arange(Q.shape[1])] = 0.0
    q = Q.sum(2)
    bt = np.swapaxes(basis, 1, 2)  # G = 2 B^T diag(q) B - 2 B^T Q B per solution, as GEMMs
    G = 2 * np.matmul(bt, basis * q[..., None]) - 2 * np.matmul(bt, np.matmul(Q, basis))
    return G, q.sum(1)


def _phase_moves(basis, step, grp, n_grp):
    """Per group: the largest phase change (rad) of any antenna of its solutions under ``step`` (n_grp, 2)."""
    moved = np.zeros(n_grp)
    np.maximum.at(moved, grp, np.abs(np.einsum("sak,sk->sa", basis, step[grp])).max(1))
    return moved


def solve_screen(X, M, W, basis, active, offsets, amplitude, groups=None, *, tol=1e-4, max_iter=30, normal=None,
                 threads=None):
    """Fit the offset and amplitude of one source in S solutions, in place.

    Parameters
    ----------
    X : ndarray (S, N, N) complex: the data with the source put back (not modified)
    M : ndarray (S, N, N) complex: the source's model coherency; W (S, N, N) real weights
    basis : ndarray (S, N, 2) (:func:`screen_basis`)
    active : bool (S,): solutions fitted; the others keep their values
    offsets, amplitude : ndarray (S, 2), (S,): start, updated in place (the active ones)
    groups : int array (S,), optional: solutions with the same id share the offset (an interval);
        default each its own
    normal : optional result of :func:`screen_normal_matrix` for these M, W, basis

    Returns
    -------
    (iterations (S,), converged (S,))
    """
    S, N = X.shape[0], X.shape[1]
    active = np.asarray(active, bool)
    groups = np.arange(S) if groups is None else np.asarray(groups)
    _, grp = np.unique(groups, return_inverse=True)
    n_grp = grp.max() + 1 if S else 0
    G, qsum = screen_normal_matrix(M, W, basis) if normal is None else normal
    use = active & (qsum > 0)
    # offsets shared within a group: start every member from the group's mean over its used members
    cnt = np.bincount(grp, use, n_grp)
    th = np.stack([np.bincount(grp, use * offsets[:, k], n_grp) for k in range(2)], 1) / np.maximum(cnt, 1)[:, None]
    grp_on = cnt > 0
    step = np.zeros((n_grp, 2))
    best = np.full(n_grp, -np.inf)
    done = ~grp_on
    iters = np.zeros(S, int)
    amp = np.zeros(S)
    sums = np.zeros((S, N), complex)
    for _ in range(max_iter + 1):
        e = np.exp(1j * np.einsum("sak,sk->sa", basis, th[grp]))
        live = use & ~done[grp]
        sums[:] = 0
        run_rows(_screen_sums, N, (X, M, W, e, live, sums), threads)
        proj = sums.real.sum(1)
        power = np.bincount(grp, np.where(live, np.maximum(proj, 0.0) ** 2 / np.where(use, qsum, 1.0), 0.0), n_grp)
        worse = ~done & (power < best * (1 - 1e-12))
        if worse.any():  # the last step lowered the fitted power: take half of it
            step[worse] *= 0.5
            th[worse] -= step[worse]
            done |= worse & (_phase_moves(basis, step, grp, n_grp) < tol)  # the halved step is negligible
            continue
        best = np.where(~done, power, best)
        amp = np.where(live, np.maximum(proj, 0.0) / np.where(use, qsum, 1.0), amp)
        b = 2 * np.einsum("sak,sa->sk", basis, sums.imag)  # per solution, for a = 1
        A = np.zeros((n_grp, 2, 2))
        r = np.zeros((n_grp, 2))
        np.add.at(A, grp, np.where(live, amp**2, 0.0)[:, None, None] * G)
        np.add.at(r, grp, np.where(live, amp, 0.0)[:, None] * b)
        on = ~done & (np.einsum("gkk->g", A) > 0)
        step = np.zeros((n_grp, 2))
        step[on] = np.einsum("gkl,gl->gk", np.linalg.pinv(A[on], rcond=1e-12, hermitian=True), r[on])
        th += step
        iters[live] += 1
        done |= _phase_moves(basis, step, grp, n_grp) < tol
        if done.all():
            break
    offsets[active] = th[grp][active]
    amplitude[active] = np.where(use, amp, 0.0)[active]
    return iters, done[grp] | ~active
