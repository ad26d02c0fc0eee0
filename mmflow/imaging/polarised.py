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

from mmflow.conventions import m_slice, n_alm, complex_dtype, stokes_sizes
from mmflow.errors import InputError
from mmflow.imaging.filters import filter_mask
from mmflow.imaging.solvers import floored_penalty
from mmflow.mmode.normal import herk_into, hermitian_full
from mmflow.mmode.polarised import CORRELATIONS, STOKES
from mmflow.mmode.polarised_transfer import FourierBuffers, baselines_per_pass, polarised_pass
from mmflow.sky.harmonics import point_sources_alm


def stokes_offsets(n_t, n_p):
    """Start of T, E, B, V in a block ``[T (n_t); E (n_p); B (n_p); V (n_p)]`` and their sizes."""
    return (0, n_t, n_t + n_p, n_t + 2 * n_p), (n_t, n_p, n_p, n_p)


@dataclass
class PolarisedNormal:
    """Per-m normal equations of the full-Stokes problem, for ``m = m0 .. m0 + len(gram) - 1``.

    Attributes
    ----------
    lmax : int
    gram : list over m of complex128 ``(N_m, N_m)`` (full Hermitian), ``N_m = L_m + 3 P_m``
        (:func:`stokes_sizes`: the unknowns ``[T (l = m..lmax); E; B; V (l = m..lmax_p)]``)
    rhs : list over m of complex128 ``(n_vec, N_m)``: one row per data vector
    vhv : ndarray ``(n_vec, lmax + 1)``: ``v^H W v`` per m (0 outside the block)
    lmax_p : int, optional
        Band limit of E, B and V (``imaging.stokes_lmax``; default ``lmax``).
    m0 : int
        The first m held (0: every m; the stokes stage streams blocks of m).
    """

    lmax: int
    gram: list
    rhs: list
    vhv: np.ndarray
    lmax_p: int = None
    m0: int = 0

    def __post_init__(self):
        self.lmax_p = self.lmax if self.lmax_p is None else min(int(self.lmax_p), self.lmax)

    @property
    def m_range(self):
        """``range`` of the m held."""
        return range(self.m0, self.m0 + len(self.gram))

    def sizes(self, m):
        """``(L_m, P_m)`` of block m (:func:`stokes_sizes`)."""
        return stokes_sizes(m, self.lmax, self.lmax_p)


def _data_rows(mmodes, k, index, m0=None):
    """``(n_vec, n_corr rows)`` data of block m for baselines ``index``: per correlation ``V_m``
    then (``m > 0``) ``conj(V_{-m})``, from m-modes ``(n_vec, n_m, 2, n_corr, n_bl)`` at index ``k``
    on their m axis (``m0``: whether m is 0, default ``k == 0``)."""
    v = mmodes[:, k, :1] if (k == 0 if m0 is None else m0) else mmodes[:, k]  # (n_vec, 1 or 2, n_corr, n_bl)
    v = v[..., index].transpose(0, 2, 1, 3)  # (n_vec, n_corr, 1 or 2, nb)
    return v.reshape(v.shape[0], -1)


def accumulate_polarised_normal(grid, b_wavelengths, mmodes=None, inv_var=None, correlations=CORRELATIONS,
                                chunk_size=None, dtype=np.float64, lmax_b=None, lmax_p=None, m_range=None,
                                lmax=None, timings=None):
    """Stream over baseline chunks: ``G_m += B_m^H W B_m``, ``r_m += B_m^H W v_m``.

    Each chunk's blocks come from the ring-FFT + GEMM path
    (:func:`mmflow.mmode.polarised_transfer.polarised_pass`) and go, row-weighted by ``sqrt(W)``,
    into one ``herk`` per m (:func:`mmflow.mmode.normal.herk_into`) on the thread that computed them.
    The columns of ``B_m`` are ``[T (l = m..lmax); E; B; V (l = m..lmax_p)]`` (:func:`stokes_sizes`):
    with ``lmax_p < lmax`` the polarised sky is band-limited to ``lmax_p`` while T keeps ``lmax``, and
    for ``m > lmax_p`` the block holds T only (the four correlations still measure it).

    Parameters
    ----------
    grid : mmflow.mmode.polarised.PolarisedGrid, or callable ``(top, index) -> PolarisedGrid``
        Exact to ``lmax + `` the fringe band limit of the longest baseline; or the grid of each chunk
        (baselines ``index``, blocks to ``l = top``), exact to ``top +`` their fringe band limit, with
        ``lmax`` given: short baselines' ring FFTs on a grid of their own size.
    b_wavelengths : ndarray (n_bl, 3)
        Baselines ``x_j - x_i`` in the sky frame at ``phi = 0``, in wavelengths
        (:func:`mmflow.mmode.transfer.baselines_in_wavelengths`).
    mmodes : ndarray ``([n_vec,] mmax + 1, 2, n_corr, n_bl)``, optional
        m-modes of the correlations (:func:`mmflow.mmode.transform.mmode_transform` of data
        binned as ``(n_bins, n_corr, n_bl)``), ``mmax >= lmax``, or only those of ``m_range``
        (``m1 - m0`` on the m axis); None: the Gram only. Used in the precision of ``dtype`` (complex64 for
        float32: ``r_m`` per chunk as ``B_m``, summed in complex128), so that the stokes stage holds a block's
        m-modes at half the bytes.
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
    lmax_p : int, optional
        Band limit of E, B and V (default ``lmax``: every Stokes parameter to ``lmax``).
    m_range : (m0, m1), optional
        Only ``m0 <= m < m1`` (default every m): the stokes stage's m blocks, each a task holding its
        own Grams only.

    lmax : int, optional
        The band limit of T (default ``grid.lmax``; needed when ``grid`` is a callable).
    timings : dict, optional
        Seconds by phase, added to (:func:`mmflow.mmode.polarised_transfer.polarised_pass`'s ``fourier_s``,
        ``mpool_s``, ...: ``mmflow bench stokes-block``).

    Returns
    -------
    PolarisedNormal
    """
    b = np.asarray(b_wavelengths, float).reshape(-1, 3)
    grid_of = grid if callable(grid) else (lambda top, index: grid)
    lmax = grid.lmax if lmax is None else int(lmax)
    n_corr, nb = len(correlations), len(b)
    lmax_p = lmax if lmax_p is None else min(int(lmax_p), lmax)
    m0, m1 = (0, lmax + 1) if m_range is None else (int(m_range[0]), min(int(m_range[1]), lmax + 1))
    mm, mm0 = None, 0
    if mmodes is not None:
        mm = np.asarray(mmodes, complex_dtype(dtype))  # in the transfer's precision, as the stage holds them
        mm = mm if mm.ndim == 5 else mm[None]
        mm0 = m0 if mm.shape[1] == m1 - m0 else 0  # the block's m-modes only
        if (mm0 == 0 and mm.shape[1] < m1) or mm.shape[3:] != (n_corr, nb):
            raise InputError("polarised imaging", "mmodes", f"shape {mm.shape[1:]} for lmax {lmax}, "
                             f"{n_corr} correlations and {nb} baselines",
                             "give m-modes (mmax + 1, 2, n_corr, n_bl) with mmax >= lmax")
    n_vec = 0 if mm is None else mm.shape[0]
    w = np.ones((n_corr, nb)) if inv_var is None else np.broadcast_to(np.asarray(inv_var, float), (n_corr, nb))
    cdtype = complex_dtype(dtype).type
    size = [sum(stokes_sizes(m, lmax, lmax_p) * np.array([1, 3])) for m in range(m0, m1)]
    gram = [np.zeros((n, n), cdtype, order="F") for n in size]
    rhs = [np.zeros((n_vec, n), np.complex128) for n in size]
    vhv = np.zeros((n_vec, lmax + 1))
    # passes sized on the largest grid (the one of the longest baselines at lmax)
    chunk_size = chunk_size or baselines_per_pass(grid_of(lmax, np.arange(nb)), n_corr, np.dtype(cdtype).itemsize,
                                                  m_range=(m0, m1), lmax_pol=lmax_p)
    lb = np.full(nb, lmax) if lmax_b is None else np.minimum(np.asarray(lmax_b, int), lmax)
    order = np.argsort(lb, kind="stable")  # chunks of like lmax_b: blocks stop at the chunk's largest
    buffers = FourierBuffers()  # every pass's Fourier arrays in the same memory
    for start in range(0, nb, chunk_size):
        index = order[start:start + chunk_size]
        top = int(lb[index].max())
        if top < m0:  # the chunk's baselines see none of this block's m
            continue
        mask = np.arange(lmax + 1)[:, None] <= lb[index][None, :] if lb[index].min() < top else None

        def consume(m, block):  # block (n_l, 4, n_corr, cols): rows (corr, +m / -m, baseline), l = m..top
            n_l, cols = block.shape[0], block.shape[-1]
            big_t, big_p = stokes_sizes(m, lmax, lmax_p)
            n_p = max(0, min(top, lmax_p) - m + 1)  # E, B, V rows of this chunk
            if mask is not None:  # coefficients above a baseline's own lmax_b are zero
                block = block * np.tile(mask[m:top + 1], (1, cols // len(index)))[:, None, None, :]
            sw = np.sqrt(np.tile(w[:, index], (1, cols // len(index)))).reshape(-1)
            rows = [block[:, 0]] + [block[:n_p, x] for x in (1, 2, 3)]  # each (n, n_corr, cols)
            xs = np.concatenate(rows).reshape(n_l + 3 * n_p, n_corr * cols) * sw.astype(cdtype)
            g = gram[m - m0]
            if (n_l, n_p) == (big_t, big_p):
                herk_into(g, xs, n_corr * cols, n_l + 3 * n_p, n_corr * cols)
            else:  # l <= top of each Stokes: the upper blocks (X <= Y) of a smaller Gram, added in place
                part = herk_into(np.zeros((n_l + 3 * n_p,) * 2, cdtype, order="F"), xs, n_corr * cols,
                                 n_l + 3 * n_p, n_corr * cols)
                (po, ps), (bo, _) = stokes_offsets(n_l, n_p), stokes_offsets(big_t, big_p)
                for x in range(4):
                    for y in range(x, 4):
                        g[bo[x]:bo[x] + ps[x], bo[y]:bo[y] + ps[y]] += part[po[x]:po[x] + ps[x], po[y]:po[y] + ps[y]]
            if mm is not None:
                v = _data_rows(mm, m - mm0, index, m == 0)
                (bo, _), (po, ps) = stokes_offsets(big_t, big_p), stokes_offsets(n_l, n_p)
                r = (v * sw.astype(np.finfo(cdtype).dtype)) @ xs.conj().T  # in the transfer's precision
                for x in range(4):
                    rhs[m - m0][:, bo[x]:bo[x] + ps[x]] += r[:, po[x]:po[x] + ps[x]]
                vhv[:, m] += np.sum(sw ** 2 * np.abs(v) ** 2, axis=1)

        polarised_pass(grid_of(top, index), b[index], consume, mmax=min(top, m1 - 1), correlations=correlations,
                       dtype=dtype, lmax_rows=top, mmin=m0, lmax_pol=lmax_p, buffers=buffers, timings=timings)
    buffers = None  # the Fourier arrays' memory freed before the Grams are completed
    for k in range(len(gram)):  # one m at a time: never two whole Grams
        gram[k] = hermitian_full(gram[k])
    return PolarisedNormal(lmax, gram, rhs, vhv, lmax_p, m0)


#: bytes per Gram element held while every m's Grams are kept with their factors: the complex128 Gram and its
#: complex128 Cholesky factor (:class:`PolarisedObserver` with ``keep_factors``)
BLOCK_BYTES_PER_ELEMENT = 32


def stokes_m_blocks(lmax, lmax_p, budget_bytes, bytes_per_m=0.0, bytes_per_element=BLOCK_BYTES_PER_ELEMENT):
    """Contiguous blocks of m ``[(m0, m1), ...]`` covering ``0..lmax`` whose normal equations fit a budget.

    Block m holds ``bytes_per_element N_m^2`` bytes (``N_m = L_m + 3 P_m``, :func:`stokes_sizes`; the
    accumulation's complex size where the block is solved one m at a time,
    :meth:`PolarisedObserver.solution_and_leakage`) and ``bytes_per_m`` (its m-modes). As few blocks as
    filling them greedily from m = 0 within ``budget_bytes`` gives, each with at least one m, balanced: the
    smallest budget that still gives that many (a greedy fill leaves a last block of a few m, which pays the ring
    stage of every long baseline again for them: 1/7 of the stage at the paper's scale). A function of the
    settings only (never of the cluster).
    """
    cost = [bytes_per_element * float(sum(stokes_sizes(m, lmax, lmax_p) * np.array([1, 3]))) ** 2 + bytes_per_m
            for m in range(lmax + 1)]
    n = len(_greedy_blocks(cost, budget_bytes))
    lo, hi = max(cost), float(budget_bytes)  # the smallest budget giving n blocks lies in [lo, hi]
    if hi <= lo:
        return _greedy_blocks(cost, budget_bytes)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if len(_greedy_blocks(cost, mid)) <= n else (mid, hi)
    return _greedy_blocks(cost, hi)


def _greedy_blocks(cost, budget):
    """Blocks ``[(m0, m1), ...]`` filled from m = 0 while the sum of ``cost[m]`` stays within ``budget``."""
    blocks, m0, used = [], 0, 0.0
    for m, b in enumerate(cost):
        if m > m0 and used + b > budget:
            blocks.append((m0, m))
            m0, used = m, 0.0
        used += b
    return blocks + [(m0, len(cost))]


#: ``eps_pol / eps`` when not given: the prior of a weakly polarised sky (docs/stokes.md)
EPS_POL_RATIO = 100.0


def stokes_eps(eps, eps_pol=None):
    """Tikhonov eps per harmonic ``(T, E, B, V)``: ``eps`` for T, ``eps_pol`` (default
    ``EPS_POL_RATIO x eps``) for E, B and V."""
    pol = float(eps_pol) if eps_pol is not None else EPS_POL_RATIO * float(eps)
    return (float(eps), pol, pol, pol)


def penalty(eps, n_l, n_p=None):
    """Diagonal of ``D`` for one m block: ``eps`` per Stokes (T, E, B, V), T's repeated ``n_l`` times and
    E's, B's, V's ``n_p`` times (default ``n_l``: every Stokes parameter to the same band limit).

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
    return np.repeat(vals, stokes_offsets(n_l, n_l if n_p is None else n_p)[1])


def _pack(alm, m, lmax, lmax_p):
    """``[T_m; E_m; B_m; V_m]`` of a ``(4, n_alm)`` alm array: T to ``lmax``, E, B, V to ``lmax_p``."""
    n_p = stokes_sizes(m, lmax, lmax_p)[1]
    sl = m_slice(lmax, m)
    return np.concatenate([alm[0, sl]] + [alm[x, sl][:n_p] for x in (1, 2, 3)])


def _unpack_into(out, y, m, lmax, lmax_p):
    """Write block-m unknowns ``y`` ``(n_vec, L_m + 3 P_m)`` into alm ``out`` ``(n_vec, 4, n_alm)``
    (E, B, V above ``lmax_p`` stay as they are: zero)."""
    (off, size), sl = stokes_offsets(*stokes_sizes(m, lmax, lmax_p)), m_slice(lmax, m)
    for x in range(4):
        out[:, x, sl.start:sl.start + size[x]] = y[:, off[x]:off[x] + size[x]]


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

    ``true_alm``: ``(4, n_alm)`` or ``(n_vec, 4, n_alm)`` T, E, B, V (E, B, V above the normal
    equations' ``lmax_p`` are outside the model and not seen); ``filters`` as in :func:`solve_polarised`.
    Returns ``(n_vec, 4, n_alm)``. With a T-only ``true_alm`` (an unpolarised sky) its E, B, V parts
    are the leakage of I into Q, U, V maps. (:class:`PolarisedObserver`, which keeps the factorisations
    for repeated calls.)
    """
    return PolarisedObserver(normal, eps, filters)(true_alm)


class PolarisedObserver:
    """The solve ``x_m = (G_m + D)^-1 r_m`` and the map of a true sky through it, ``x -> (G_m + D)^-1 G_m x_m``,
    for the m of ``normal`` (:attr:`PolarisedNormal.m_range`) from the Cholesky factors of ``G_m + D``
    (the stokes stage solves, images the leakage and CLEANs V with one set); ``filters`` remove unknowns
    (zero in every Stokes parameter) as in :func:`solve_polarised`, and ``D`` is :func:`penalty`
    (:func:`mmflow.imaging.solvers.floored_penalty`).

    ``keep_factors``: factorise every m once, here, and keep the factors (the size of the Gram); False:
    factorise each m again at every call and keep none, so that only one m's Gram and factor are in
    memory at a time (``normal.gram`` may then be a sequence read from disk per m: the stokes stage's
    second phase at the paper's scale); a collection of m: keep those m's factors only (the stokes stage keeps
    the largest that fit its budget, :func:`mmflow.workflow.stages.stokes.blocks.factors_kept`). The results are
    the same bits either way.
    """

    def __init__(self, normal, eps, filters=None, keep_factors=True):
        self.normal, self.eps, self.filters = normal, eps, filters
        self.lmax, self.lmax_p = normal.lmax, normal.lmax_p
        kept = set(normal.m_range) if keep_factors is True else set(keep_factors or ())
        self.blocks = {m: self._factor(m) for m in normal.m_range if m in kept}

    def _block(self, m):
        """Block m's kept factor, or the factor made now (:meth:`_factor`)."""
        return self.blocks[m] if m in self.blocks else self._factor(m)

    def _factor(self, m):
        """``(keep, cho_factor(G_kk + D_k))`` of block m, or None when the filters remove all of it."""
        n_l, n_p = self.normal.sizes(m)
        keep = np.ones(n_l + 3 * n_p, bool)
        if self.filters:
            fm = filter_mask(m, self.lmax, **self.filters)
            keep = np.concatenate([fm] + [fm[:n_p]] * 3)
        if not keep.any():
            return None
        g = np.asarray(self.normal.gram[m - self.normal.m0])[np.ix_(keep, keep)].astype(np.complex128)
        g[np.diag_indices(len(g))] += floored_penalty(penalty(self.eps, n_l, n_p)[keep])
        return keep, sla.cho_factor(g, overwrite_a=True, check_finite=False)

    def solve(self, rhs_of_m):
        """``(G_m + D)^-1 r_m`` for every m held, ``rhs_of_m(m)`` ``(n_vec, L_m + 3 P_m)``:
        alm ``(n_vec, 4, n_alm)`` (zero at the m not held)."""
        out = None
        for m in self.normal.m_range:
            block = self._block(m)
            rhs = rhs_of_m(m)
            if out is None:
                out = np.zeros((len(rhs), 4, n_alm(self.lmax)), np.complex128)
            if block is not None:
                _unpack_into(out, _solved(block, rhs), m, self.lmax, self.lmax_p)
        return out

    def solution(self):
        """The solve of the data: ``(G_m + D)^-1 r_m`` of every data vector, ``(n_vec, 4, n_alm)``."""
        return self.solve(lambda m: self.normal.rhs[m - self.normal.m0])

    def solution_and_leakage(self):
        """:meth:`solution` and the image of its first vector's unpolarised part through the solve: ``self([T, 0,
        0, 0])`` with ``T`` the solution's, ``((n_vec, 4, n_alm), (4, n_alm))``; each m factorised once, so that
        without ``keep_factors`` one m's factor is in memory at a time (the stokes stage's block tasks). The same
        bits as :meth:`solution` then ``self`` of its unpolarised part."""
        out = leak = None
        for m in self.normal.m_range:
            block = self._block(m)
            rhs = self.normal.rhs[m - self.normal.m0]
            if out is None:
                out, leak = (np.zeros((n, 4, n_alm(self.lmax)), np.complex128) for n in (len(rhs), 1))
            if block is None:
                continue
            _unpack_into(out, _solved(block, rhs), m, self.lmax, self.lmax_p)
            n_p = self.normal.sizes(m)[1]  # [T_m; 0; 0; 0] of the first solution (:func:`_pack`)
            t = np.concatenate([out[0, 0, m_slice(self.lmax, m)], np.zeros(3 * n_p, np.complex128)])
            _unpack_into(leak, _solved(block, self._gram_times(m, t[None])), m, self.lmax, self.lmax_p)
        return out, leak[0]

    def _gram_times(self, m, packed):
        """``G_m x`` of packed block-m unknowns ``(n_vec, N_m)``: ``(n_vec, N_m)`` (one product for many)."""
        g = np.asarray(self.normal.gram[m - self.normal.m0])
        return (g @ packed[0])[None] if len(packed) == 1 else (g @ packed.T).T

    def __call__(self, true_alm):
        """The noiseless image through the solve of ``(4, n_alm)`` or ``(n_vec, 4, n_alm)`` true harmonics
        (the Gram's own product, no copy of it: one factor per m is the extra memory)."""
        x = np.asarray(true_alm)
        x = x if x.ndim == 3 else x[None]

        def rhs(m):  # the Gram read once per m (it may come from disk: the stokes stage's stored Grams)
            return self._gram_times(m, np.stack([_pack(xx, m, self.lmax, self.lmax_p) for xx in x]))
        return self.solve(rhs)


def _solved(block, rhs):
    """``(G_m + D)^-1 r`` on a block's kept unknowns (zero at those the filters remove), ``block`` a
    :meth:`PolarisedObserver._factor`, ``rhs`` ``(n_vec, N_m)``."""
    keep, factor = block
    y = np.zeros((len(rhs), len(keep)), np.complex128)
    y[:, keep] = sla.cho_solve(factor, rhs[:, keep].T, check_finite=False).T
    return y


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


def stokes_at(alm, vecs, lmax, epsilon=1e-10):
    """IAU ``(I, Q, U, V)`` of ``(T, E, B, V)`` alm ``(4, n_alm)`` at unit vectors ``vecs`` ``(n, 3)``: ``(n, 4)``.

    The maps of :func:`stokes_maps` read exactly at the points (no pixels): ducc0's spin-0 synthesis of T
    and V and spin-2 synthesis of ``(E, B)`` at the points (``(Q, U_healpy)``, ``U = -U_healpy``).
    """
    vec = np.asarray(vecs, float).reshape(-1, 3)
    loc = np.stack([np.arccos(np.clip(vec[:, 2] / np.linalg.norm(vec, axis=1), -1, 1)),
                    np.mod(np.arctan2(vec[:, 1], vec[:, 0]), 2 * np.pi)], axis=1)
    a = np.asarray(alm, np.complex128)

    def at(x, spin):
        return ducc0.sht.synthesis_general(alm=np.ascontiguousarray(x), spin=spin, lmax=lmax, loc=loc,
                                           epsilon=epsilon)
    q, u_h = at(a[1:3], 2)
    return np.stack([at(a[:1], 0)[0], q, -u_h, at(a[3:], 0)[0]], axis=1)


def stokes_response(observe, decs_rad, stokes=(0, 1, 2, 3)):
    """The images of unit point sources through the solve: the run's own resolution matrix.

    At each declination (RA 0, frame of date; the drift scan makes the response the same at every RA,
    turned by ``exp(-i m ra)``) one noiseless point source of unit Stokes X for each X in ``stokes``
    (indices of ``(I, Q, U, V)``) is imaged through ``observe``
    (:class:`PolarisedObserver`: ``(G_m + D)^-1 G_m x_m``). Returns ``(n_dec, len(stokes), 4 [T, E, B, V],
    n_alm)``. The polarisation response, the V PSF and the full-Stokes CLEAN's response matrices are read
    from it (:func:`polarisation_response`, :func:`response_matrices`,
    :func:`mmflow.imaging.polarised_clean.v_psf_table`).
    """
    lmax = observe.lmax
    decs = np.asarray(decs_rad, float).reshape(-1)
    vec = np.stack([np.cos(decs), np.zeros_like(decs), np.sin(decs)], axis=-1)
    truth = np.stack([point_source_stokes_alm(v, np.eye(4)[x], lmax) for v in vec for x in stokes])
    return observe(truth).reshape(len(decs), len(stokes), 4, -1)


def response_matrices(images, decs_rad, lmax, stokes=(0, 1, 2, 3)):
    """``A (n_dec, 4, 4)``: ``A[d, X, Y]`` the Stokes-X map at the source of a unit Stokes-Y point source at
    declination ``d`` (RA 0), from :func:`stokes_response`'s ``images`` of the sources ``stokes`` (read exactly
    at the source, :func:`stokes_at`; the columns of the others 0). A source of Stokes vector ``s`` there
    images as ``A s`` at its position."""
    decs = np.asarray(decs_rad, float).reshape(-1)
    vec = np.stack([np.cos(decs), np.zeros_like(decs), np.sin(decs)], axis=-1)
    out = np.zeros((len(decs), 4, 4))
    for d, v in enumerate(vec):
        for k, y in enumerate(stokes):
            out[d, :, y] = stokes_at(images[d, k], v, lmax)[0]
    return out


#: what :func:`polarisation_response` calls measured: each test fraction recovered within this of 1 ...
RESPONSE_TOLERANCE = 0.05
#: ... and the unpolarised test source's Q, U, V below this fraction of its I
LEAKAGE_TOLERANCE = 0.005


def polarisation_response(observe, decs_rad, fraction=0.1):
    """What the solve's maps make of polarised point sources: the resolution matrix at test sources.

    At each declination (RA 0, frame of date) four noiseless point sources are imaged through
    ``observe`` (:class:`PolarisedObserver`, the run's operator, eps and filters): unpolarised
    ``(1, 0, 0, 0)`` and ``(1, f, 0, 0)``, ``(1, 0, f, 0)``, ``(1, 0, 0, f)``. Read at the source
    (:func:`response_matrices`: the test source ``t`` images as ``A t``)::

        leakage  = max(|Q_0|, |U_0|, |V_0|) / I_0            (the unpolarised source)
        ratio_X  = (X_X / I_X - X_0 / I_0) / f,   X = Q, U, V  (1: the fraction imaged as it is)

    With Q, U, V band-limited below I (``observe.lmax_p < observe.lmax``, ``imaging.stokes_lmax``) the
    fractions are taken against I at the same band limit (``I`` with its ``l > lmax_p`` set to 0), as a
    fraction map must be: a point source's peak at ``lmax_p`` is lower than at ``lmax`` by the
    resolution alone (at lmax 32: 0.87-0.92 of it at ``lmax_p`` 24, 0.40-0.43 at 16).

    This is about the maps (``stokes_<tag>.fits``, ``polfrac_<tag>.fits``); the full-Stokes CLEAN's sources
    (:func:`mmflow.imaging.polarised_clean.clean_stokes`) invert ``A`` and are unbiased where it is
    well conditioned, whatever this says.

    Parameters
    ----------
    observe : PolarisedObserver
    decs_rad : sequence of float
    fraction : float
        The test sources' polarised fraction ``f``.

    Returns
    -------
    dict: ``dec_deg``, ``leakage``, ``ratio_q``, ``ratio_u``, ``ratio_v`` (lists over declinations),
    ``measured`` (every ratio within :data:`RESPONSE_TOLERANCE` of 1 and every leakage below
    :data:`LEAKAGE_TOLERANCE`) and ``note`` (why not, when not).
    """
    lmax, lmax_p = observe.lmax, observe.lmax_p
    decs = np.asarray(decs_rad, float).reshape(-1)
    images = stokes_response(observe, decs)
    if lmax_p < lmax:  # I at the polarised band limit, for the fractions
        images[..., 0, healpy.Alm.getlm(lmax)[0] > lmax_p] = 0
    tests = np.vstack([np.eye(4)[0]] + [np.eye(4)[0] + fraction * np.eye(4)[k] for k in (1, 2, 3)])
    out = {"dec_deg": np.rad2deg(decs).round(3).tolist(), "fraction": float(fraction), "leakage": [],
           "ratio_q": [], "ratio_u": [], "ratio_v": []}
    for a in response_matrices(images, decs, lmax):
        at = tests @ a.T  # (test, IQUV)
        frac = at[:, 1:] / at[:, :1]
        out["leakage"].append(float(np.abs(frac[0]).max()))
        for k, name in enumerate(("ratio_q", "ratio_u", "ratio_v")):
            out[name].append(float((frac[k + 1, k] - frac[0, k]) / fraction))
    ratios = np.array([out[n] for n in ("ratio_q", "ratio_u", "ratio_v")])
    worst_ratio = float(ratios.flat[np.argmax(np.abs(ratios - 1))])
    worst_leak = float(max(out["leakage"]))
    out["measured"] = bool(abs(worst_ratio - 1) <= RESPONSE_TOLERANCE and worst_leak < LEAKAGE_TOLERANCE)
    out["note"] = "" if out["measured"] else (
        f"the maps do not image polarisation as it is at this lmax and eps: Q, U, V fractions image at "
        f"{worst_ratio:.2f} of the truth (worst test declination) and an unpolarised source leaks "
        f"{worst_leak:.2%} of I into Q, U, V; the polarised maps are not fractions of the sky (the CLEANed "
        f"sources' fractions are, where their response is measured: 'sources')")
    return out
