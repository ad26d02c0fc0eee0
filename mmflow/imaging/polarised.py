"""Full-Stokes m-mode imaging: normal equations over ``[T, E, B, V]`` and Tikhonov per Stokes.

For each m the four correlations' m-modes of every baseline are stacked against the four
Stokes harmonics (:mod:`mmflow.mmode.polarised`, IAU sky, healpy E/B)::

    v_m = [v_m^xx; v_m^yy; v_m^xy; v_m^yx],     v_m^pq = sum_X B_m^{pq,X} x_m^X,
    B_m = [[B^{xx,T} B^{xx,E} B^{xx,B} B^{xx,V}],
           [   ...                            ],
           [B^{yx,T} B^{yx,E} B^{yx,B} B^{yx,V}]],   x_m = [T_m; E_m; B_m; V_m],

each ``v_m^pq`` in the Stokes-I row layout (``V_m`` rows, then ``conj(V_{-m})`` rows for
``m > 0``) and each ``x_m^X`` the harmonics ``l = m..lmax``. Normal equations
``G_m = B_m^H W B_m``, ``r_m = B_m^H W v_m`` (``W`` diagonal, one inverse variance per
correlation and baseline) are accumulated over baseline chunks, never storing ``B``, and solved
with a Tikhonov penalty per Stokes parameter::

    x_m = (G_m + D)^-1 r_m,    D = diag(eps_T 1_L, eps_E 1_L, eps_B 1_L, eps_V 1_L),

(the Cholesky factors of :class:`PolarisedObserver`, ``D`` floored as
:func:`mmflow.imaging.solvers.floored_penalty`); usually ``eps_E = eps_B = eps_pol``. E and B
harmonics with ``l < 2`` do not exist: their columns are zero and the penalty keeps them zero.
The noiseless image of a true sky ``x`` through the same operator is ``(G_m + D)^-1 G_m x_m``
(the resolution matrix, :func:`expected_alm`): comparing a map with it is exact in the
noiseless limit.

Maps. ``I`` and ``V`` from ``T`` and ``V``; ``Q`` and ``U`` from ``E``, ``B`` through healpy's
spin-2 synthesis, which is the COSMO convention: ``U_IAU = -U_healpy`` (:func:`stokes_maps`).
"""
from __future__ import annotations

from dataclasses import dataclass

import ducc0
import healpy
import numpy as np
import scipy.linalg as sla

from mmflow.conventions import m_slice, n_alm, complex_dtype
from mmflow.errors import InputError
from mmflow.imaging.filters import filter_mask
from mmflow.imaging.solvers import floored_penalty
from mmflow.mmode.normal import herk_into, hermitian_full
from mmflow.mmode.polarised import CORRELATIONS, STOKES
from mmflow.mmode.polarised_transfer import baselines_per_pass, polarised_pass
from mmflow.sky.harmonics import point_sources_alm


@dataclass
class PolarisedNormal:
    """Per-m normal equations of the full-Stokes problem.

    Attributes
    ----------
    lmax : int
    gram : list over m of complex128 ``(4 L_m, 4 L_m)`` (full Hermitian), ``L_m = lmax - m + 1``
    rhs : list over m of complex128 ``(n_vec, 4 L_m)``: one row per data vector
    vhv : ndarray ``(n_vec, lmax + 1)``: ``v^H W v`` per m
    """

    lmax: int
    gram: list
    rhs: list
    vhv: np.ndarray


def _data_rows(mmodes, m, index):
    """``(n_vec, n_corr rows)`` data of block m for baselines ``index``: per correlation ``V_m``
    then (``m > 0``) ``conj(V_{-m})``, from m-modes ``(n_vec, mmax + 1, 2, n_corr, n_bl)``."""
    v = mmodes[:, m, :1] if m == 0 else mmodes[:, m]  # (n_vec, 1 or 2, n_corr, n_bl)
    v = v[..., index].transpose(0, 2, 1, 3)  # (n_vec, n_corr, 1 or 2, nb)
    return v.reshape(v.shape[0], -1)


def accumulate_polarised_normal(grid, b_wavelengths, mmodes=None, inv_var=None, correlations=CORRELATIONS,
                                chunk_size=None, dtype=np.float64, lmax_b=None):
    """Stream over baseline chunks: ``G_m += B_m^H W B_m``, ``r_m += B_m^H W v_m``.

    Each chunk's blocks come from the ring-FFT + GEMM path
    (:func:`mmflow.mmode.polarised_transfer.polarised_pass`) and go, row-weighted by ``sqrt(W)``,
    into one ``herk`` per m (:func:`mmflow.mmode.normal.herk_into`) on the thread that computed them.

    Parameters
    ----------
    grid : mmflow.mmode.polarised.PolarisedGrid
        Exact to ``lmax + `` the fringe band limit of the longest baseline.
    b_wavelengths : ndarray (n_bl, 3)
        Baselines ``x_j - x_i`` in the sky frame at ``phi = 0``, in wavelengths
        (:func:`mmflow.mmode.transfer.baselines_in_wavelengths`).
    mmodes : ndarray ``([n_vec,] mmax + 1, 2, n_corr, n_bl)``, optional
        m-modes of the correlations (:func:`mmflow.mmode.transform.mmode_transform` of data
        binned as ``(n_bins, n_corr, n_bl)``), ``mmax >= grid.lmax``; None: the Gram only.
    inv_var : ndarray ``(n_corr, n_bl)``, optional
        Inverse noise variance of each correlation's m-modes (default 1).
    correlations : sequence of str
        The correlations on the m-modes' correlation axis.
    chunk_size : int, optional
        Baselines per transfer pass (default
        :func:`mmflow.mmode.polarised_transfer.baselines_per_pass`).
    dtype : float64 or float32
        Precision of the transfer blocks and of the accumulation (the Grams are returned complex128).
    lmax_b : ndarray (n_bl,), optional
        Per-baseline lmax (:meth:`mmflow.telescope.Telescope.baseline_lmax`, as the Stokes-I path's
        ``transfer.per_baseline_lmax``): a baseline's coefficients above it are zero, and its chunk's
        blocks (baselines sorted by ``lmax_b``) stop at the chunk's largest (Legendre GEMMs and
        ``herk`` over ``l <= lmax_c`` only; the ring FFTs stay on ``grid``). Its m-modes enter ``r_m``
        and ``v^H W v`` for ``m <= lmax_c``.

    Returns
    -------
    PolarisedNormal
    """
    b = np.asarray(b_wavelengths, float).reshape(-1, 3)
    lmax, n_corr, nb = grid.lmax, len(correlations), len(b)
    mm = None
    if mmodes is not None:
        mm = np.asarray(mmodes)
        mm = mm if mm.ndim == 5 else mm[None]
        if mm.shape[1] <= lmax or mm.shape[3:] != (n_corr, nb):
            raise InputError("polarised imaging", "mmodes", f"shape {mm.shape[1:]} for lmax {lmax}, "
                             f"{n_corr} correlations and {nb} baselines",
                             "give m-modes (mmax + 1, 2, n_corr, n_bl) with mmax >= lmax")
    n_vec = 0 if mm is None else mm.shape[0]
    w = np.ones((n_corr, nb)) if inv_var is None else np.broadcast_to(np.asarray(inv_var, float), (n_corr, nb))
    cdtype = complex_dtype(dtype).type
    gram = [np.zeros((4 * (lmax - m + 1),) * 2, cdtype, order="F") for m in range(lmax + 1)]
    rhs = [np.zeros((n_vec, 4 * (lmax - m + 1)), np.complex128) for m in range(lmax + 1)]
    vhv = np.zeros((n_vec, lmax + 1))
    chunk_size = chunk_size or baselines_per_pass(grid, n_corr, np.dtype(cdtype).itemsize)
    lb = np.full(nb, lmax) if lmax_b is None else np.minimum(np.asarray(lmax_b, int), lmax)
    order = np.argsort(lb, kind="stable")  # chunks of like lmax_b: blocks stop at the chunk's largest
    for start in range(0, nb, chunk_size):
        index = order[start:start + chunk_size]
        top = int(lb[index].max())
        mask = np.arange(lmax + 1)[:, None] <= lb[index][None, :] if lb[index].min() < top else None

        def consume(m, block):  # block (n_l, 4, n_corr, cols): rows (corr, +m / -m, baseline), l = m..top
            n_l, cols, big = block.shape[0], block.shape[-1], lmax - m + 1
            if mask is not None:  # coefficients above a baseline's own lmax_b are zero
                block = block * np.tile(mask[m:top + 1], (1, cols // len(index)))[:, None, None, :]
            sw = np.sqrt(np.tile(w[:, index], (1, cols // len(index)))).reshape(-1)
            xs = block.transpose(1, 0, 2, 3).reshape(4 * n_l, n_corr * cols) * sw.astype(cdtype)
            if n_l == big:
                herk_into(gram[m], xs, n_corr * cols, 4 * n_l, n_corr * cols)
            else:  # l = m..top of each Stokes: the upper blocks (X <= Y) of a smaller Gram, added in place
                part = herk_into(np.zeros((4 * n_l,) * 2, cdtype, order="F"), xs, n_corr * cols, 4 * n_l,
                                 n_corr * cols)
                for x in range(4):
                    for y in range(x, 4):
                        gram[m][x * big:x * big + n_l, y * big:y * big + n_l] += \
                            part[x * n_l:(x + 1) * n_l, y * n_l:(y + 1) * n_l]
            if mm is not None:
                v = _data_rows(mm, m, index)
                rhs[m].reshape(n_vec, 4, big)[:, :, :n_l] += ((v * sw) @ xs.conj().T).reshape(n_vec, 4, n_l)
                vhv[:, m] += np.sum(sw ** 2 * np.abs(v) ** 2, axis=1)

        polarised_pass(grid, b[index], consume, mmax=top, correlations=correlations, dtype=dtype, lmax_rows=top)
    for m in range(lmax + 1):  # one m at a time: never two whole Grams
        gram[m] = hermitian_full(gram[m])
    return PolarisedNormal(lmax, gram, rhs, vhv)


#: ``eps_pol / eps`` when not given: the prior of a weakly polarised sky (docs/stokes.md)
EPS_POL_RATIO = 100.0


def stokes_eps(eps, eps_pol=None):
    """Tikhonov eps per harmonic ``(T, E, B, V)``: ``eps`` for T, ``eps_pol`` (default
    ``EPS_POL_RATIO x eps``) for E, B and V."""
    pol = float(eps_pol) if eps_pol is not None else EPS_POL_RATIO * float(eps)
    return (float(eps), pol, pol, pol)


def penalty(eps, n_l):
    """Diagonal of ``D`` for one m block: ``eps`` per Stokes (T, E, B, V), each repeated ``n_l`` times.

    ``eps``: a dict ``{"T": .., "E": .., "B": .., "V": ..}``, a 4-sequence, or a pair
    ``(eps_I, eps_pol)`` (``eps_pol`` for E, B and V).
    """
    if isinstance(eps, dict):
        vals = [float(eps[x]) for x in STOKES]
    else:
        vals = [float(e) for e in np.atleast_1d(eps)]
        if len(vals) == 2:
            vals = [vals[0], vals[1], vals[1], vals[1]]
    if len(vals) != 4 or min(vals) <= 0:
        raise InputError("polarised imaging", "eps", f"{eps}",
                         "give four positive values (T, E, B, V) or (eps_I, eps_pol)")
    return np.repeat(vals, n_l)


def _pack(alm, m, lmax):
    """``[T_m; E_m; B_m; V_m]`` (l = m..lmax each) of a ``(4, n_alm)`` alm array."""
    return np.concatenate([alm[x, m_slice(lmax, m)] for x in range(4)])


def solve_polarised(normal, eps, filters=None):
    """``x_m = (G_m + D)^-1 r_m`` for every m and data vector: alm ``(n_vec, 4 [T, E, B, V], n_alm)``.

    Parameters
    ----------
    normal : PolarisedNormal
    eps : see :func:`penalty`
    filters : dict, optional
        Keyword arguments of :func:`mmflow.imaging.filters.filter_mask` (the m-filters of the
        Stokes-I solve): the unknowns they remove are removed from every Stokes parameter (zero).
    """
    return PolarisedObserver(normal, eps, filters).solution()


def expected_alm(normal, true_alm, eps, filters=None):
    """The noiseless image of a true sky through the same solve: ``(G_m + D)^-1 G_m x_m``.

    ``true_alm``: ``(4, n_alm)`` or ``(n_vec, 4, n_alm)`` T, E, B, V band-limited to ``lmax``;
    ``filters`` as in :func:`solve_polarised`. Returns ``(n_vec, 4, n_alm)``. With a T-only
    ``true_alm`` (an unpolarised sky) its E, B, V parts are the leakage of I into Q, U, V maps.
    (:class:`PolarisedObserver`, which keeps the factorisations for repeated calls.)
    """
    return PolarisedObserver(normal, eps, filters)(true_alm)


class PolarisedObserver:
    """The solve ``x_m = (G_m + D)^-1 r_m`` and the map of a true sky through it, ``x -> (G_m + D)^-1 G_m x_m``,
    for every m from the Cholesky factors of ``G_m + D`` computed once (the stokes stage solves, images the
    leakage and CLEANs V with one set); ``filters`` remove unknowns (zero in every Stokes parameter) as in
    :func:`solve_polarised`, and ``D`` is :func:`penalty` (:func:`mmflow.imaging.solvers.floored_penalty`)."""

    def __init__(self, normal, eps, filters=None):
        self.normal = normal
        self.lmax = normal.lmax
        self.blocks = []
        for m in range(self.lmax + 1):
            n_l = self.lmax - m + 1
            keep = np.tile(filter_mask(m, self.lmax, **filters), 4) if filters else np.ones(4 * n_l, bool)
            if not keep.any():
                self.blocks.append(None)
                continue
            g = normal.gram[m][np.ix_(keep, keep)]
            g[np.diag_indices(len(g))] += floored_penalty(penalty(eps, n_l)[keep])
            self.blocks.append((keep, sla.cho_factor(g, overwrite_a=True, check_finite=False)))

    def solve(self, rhs_of_m):
        """``(G_m + D)^-1 r_m`` for every m, ``rhs_of_m(m)`` ``(n_vec, 4 (lmax - m + 1))``:
        alm ``(n_vec, 4, n_alm)``."""
        n_vec = len(rhs_of_m(0))
        out = np.zeros((n_vec, 4, n_alm(self.lmax)), np.complex128)
        for m, block in enumerate(self.blocks):
            if block is None:
                continue
            keep, factor = block
            rhs = rhs_of_m(m)
            y = np.zeros((n_vec, len(keep)), np.complex128)
            y[:, keep] = sla.cho_solve(factor, rhs[:, keep].T, check_finite=False).T
            out[:, :, m_slice(self.lmax, m)] = y.reshape(n_vec, 4, -1)
        return out

    def solution(self):
        """The solve of the data: ``(G_m + D)^-1 r_m`` of every data vector, ``(n_vec, 4, n_alm)``."""
        return self.solve(lambda m: self.normal.rhs[m])

    def __call__(self, true_alm):
        """The noiseless image through the solve of ``(4, n_alm)`` or ``(n_vec, 4, n_alm)`` true harmonics
        (the Gram's own product, no copy of it: one factor per m is the extra memory)."""
        x = np.asarray(true_alm)
        x = x if x.ndim == 3 else x[None]
        return self.solve(lambda m: np.stack([self.normal.gram[m] @ _pack(xx, m, self.lmax) for xx in x]))


def point_source_stokes_alm(vectors, stokes_jy, lmax, epsilon=1e-12):
    """``(T, E, B, V)`` harmonics (Jy/sr, healpy layout) of IAU point sources ``sum_s S_s delta(r - r_s)``.

    ``T_lm = sum I_s conj(Y_lm(r_s))``, ``V_lm`` likewise; E and B are the adjoint spin-2 synthesis
    of the point values ``(Q, U_healpy = -U)`` (the spin-2 analysis of delta functions), by ducc0
    to relative accuracy ``epsilon``.
    """
    vec = np.asarray(vectors, float).reshape(-1, 3)
    st = np.asarray(stokes_jy, float).reshape(-1, 4)
    theta = np.arccos(np.clip(vec[:, 2] / np.linalg.norm(vec, axis=1), -1, 1))
    phi = np.mod(np.arctan2(vec[:, 1], vec[:, 0]), 2 * np.pi)
    eb = ducc0.sht.adjoint_synthesis_general(map=np.stack([st[:, 1], -st[:, 2]]), spin=2, lmax=lmax,
                                             loc=np.stack([theta, phi], axis=1), epsilon=epsilon)
    return np.stack([point_sources_alm(vec, st[:, 0], lmax), eb[0], eb[1], point_sources_alm(vec, st[:, 3], lmax)])


def stokes_maps(alm, nside, lmax):
    """HEALPix ``(I, Q, U, V)`` maps (IAU) from ``(T, E, B, V)`` alm ``(4, n_alm)``.

    ``I, Q, U_healpy = alm2map([T, E, B], pol=True)``, ``U = -U_healpy``, ``V = alm2map(V)``.
    """
    alm = np.asarray(alm, np.complex128)
    i, q, u_h = healpy.alm2map(alm[:3], nside, lmax=lmax, pol=True)
    return np.stack([i, q, -u_h, healpy.alm2map(alm[3], nside, lmax=lmax)])


#: what :func:`polarisation_response` calls measured: each test fraction recovered within this of 1 ...
RESPONSE_TOLERANCE = 0.05
#: ... and the unpolarised test source's Q, U, V below this fraction of its I
LEAKAGE_TOLERANCE = 0.005


def polarisation_response(observe, decs_rad, nside, fraction=0.1):
    """What the solve makes of polarised point sources: the resolution matrix at test sources.

    At each declination (RA 0, frame of date) four noiseless point sources are imaged through
    ``observe`` (:class:`PolarisedObserver`, the run's operator, eps and filters): unpolarised
    ``(1, 0, 0, 0)`` and ``(1, f, 0, 0)``, ``(1, 0, f, 0)``, ``(1, 0, 0, f)``. At the source's pixel::

        leakage  = max(|Q_0|, |U_0|, |V_0|) / I_0            (the unpolarised source)
        ratio_X  = (X_X / I_X - X_0 / I_0) / f,   X = Q, U, V  (1: the fraction imaged as it is)

    Parameters
    ----------
    observe : PolarisedObserver
    decs_rad : sequence of float
    nside : int
        HEALPix resolution of the maps the values are read from (``>= lmax / 2`` or so).
    fraction : float
        The test sources' polarised fraction ``f``.

    Returns
    -------
    dict: ``dec_deg``, ``leakage``, ``ratio_q``, ``ratio_u``, ``ratio_v`` (lists over declinations),
    ``measured`` (every ratio within :data:`RESPONSE_TOLERANCE` of 1 and every leakage below
    :data:`LEAKAGE_TOLERANCE`) and ``note`` (why not, when not).
    """
    lmax = observe.lmax
    decs = np.asarray(decs_rad, float).reshape(-1)
    vec = np.stack([np.cos(decs), np.zeros_like(decs), np.sin(decs)], axis=-1)
    tests = np.vstack([np.eye(4)[0]] + [np.eye(4)[0] + fraction * np.eye(4)[k] for k in (1, 2, 3)])
    truth = np.stack([point_source_stokes_alm(v, t, lmax) for v in vec for t in tests])
    images = observe(truth).reshape(len(decs), 4, 4, -1)
    out = {"dec_deg": np.rad2deg(decs).round(3).tolist(), "fraction": float(fraction), "leakage": [],
           "ratio_q": [], "ratio_u": [], "ratio_v": []}
    for d, v in enumerate(vec):
        pix = healpy.vec2pix(nside, *v)
        at = np.stack([stokes_maps(images[d, k], nside, lmax)[:, pix] for k in range(4)])  # (test, IQUV)
        frac = at[:, 1:] / at[:, :1]
        out["leakage"].append(float(np.abs(frac[0]).max()))
        for k, name in enumerate(("ratio_q", "ratio_u", "ratio_v")):
            out[name].append(float((frac[k + 1, k] - frac[0, k]) / fraction))
    ratios = np.array([out[n] for n in ("ratio_q", "ratio_u", "ratio_v")])
    worst_ratio = float(ratios.flat[np.argmax(np.abs(ratios - 1))])
    worst_leak = float(max(out["leakage"]))
    out["measured"] = bool(abs(worst_ratio - 1) <= RESPONSE_TOLERANCE and worst_leak < LEAKAGE_TOLERANCE)
    out["note"] = "" if out["measured"] else (
        f"the array does not measure polarisation at this lmax and eps: Q, U, V fractions image at "
        f"{worst_ratio:.2f} of the truth (worst test declination) and an unpolarised source leaks "
        f"{worst_leak:.2%} of I into Q, U, V; the polarised maps are not fractions of the sky")
    return out
