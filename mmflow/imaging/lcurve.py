"""L-curves from ``G = B^H B``, ``r = B^H v`` and ``v^H v`` alone (no refactorisation of B).

With ``G = V diag(s) V^H`` and ``c = V^H r``, the Tikhonov solution for each eps gives

``||a||^2 = sum |c_i|^2 / (s_i + eps)^2``,
``||v - B a||^2 = v^H v - 2 sum |c_i|^2 / (s_i + eps) + sum s_i |c_i|^2 / (s_i + eps)^2``.

Summed over m blocks (m > 0 blocks count the ``+m`` and ``-m`` rows already), these are
the two axes of the paper's L-curve (Fig. 2).
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla


def hermitian_eig(gram):
    """``(s, V)`` with ``G = V diag(s) V^H`` (ascending ``s``) of a Hermitian ``G``: LAPACK's ``?heevd``
    (divide and conquer) through scipy.

    numpy's ``eigh`` calls the same routine but allocates its copy of ``G`` and its work arrays outside
    numpy, where ``tracemalloc`` does not see them; scipy's are numpy arrays, so a task's traced peak
    (:mod:`mmflow.workflow.engine.resources`) holds them: the copy that becomes ``V`` and ``~2 n^2``
    elements of work, three ``n x n`` complex arrays beside ``G``. ``?heevr`` needs only two but took
    ~1.3x as long on the paper channel's Grams (n ~ 1000, one thread: 0.46 s against 0.34 s).
    """
    return sla.eigh(gram, driver="evd", check_finite=False)


def default_eps_grid(n=200, lo=1e-6, hi=1e4):
    """200 logarithmically spaced trial values, as in the paper."""
    return np.logspace(np.log10(lo), np.log10(hi), n)


def lcurve_block(gram, rhs, vhv, eps_values, eig=None):
    """``(solution_norm2, residual_norm2)`` arrays for one block and all ``eps_values``.

    ``eig``: :func:`hermitian_eig` of ``gram`` when the caller already has it.
    """
    s, v = hermitian_eig(gram) if eig is None else eig
    s = np.clip(s, 0, None)
    c2 = np.abs(v.conj().T @ rhs) ** 2
    e = np.asarray(eps_values, float)[:, None]
    sol = np.sum(c2 / (s + e) ** 2, axis=1)
    res = vhv - 2 * np.sum(c2 / (s + e), axis=1) + np.sum(s * c2 / (s + e) ** 2, axis=1)
    return sol, np.maximum(res, 0.0)


def lcurve_corner(sol_norm2, res_norm2, eps_values):
    """eps at the point of maximum curvature of ``(log ||v - Ba||, log ||a||)``."""
    x = 0.5 * np.log(np.maximum(res_norm2, 1e-300))
    y = 0.5 * np.log(np.maximum(sol_norm2, 1e-300))
    t = np.log(eps_values)
    dx, dy = np.gradient(x, t), np.gradient(y, t)
    ddx, ddy = np.gradient(dx, t), np.gradient(dy, t)
    kappa = (dx * ddy - dy * ddx) / np.maximum((dx**2 + dy**2) ** 1.5, 1e-300)
    return float(eps_values[int(np.argmax(np.abs(kappa[2:-2]))) + 2])
