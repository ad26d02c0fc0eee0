"""Drift-scan visibilities of all four linear correlations from polarised point sources.

Direct sum of the measurement equation, per sidereal angle ``phi`` (no harmonics): for the
pair ``(i, j)`` (baseline ``b = x_j - x_i``, ENU, metres) and feeds ``p`` of antenna ``i``,
``q`` of antenna ``j``::

    V_pq(phi) = sum_s J_p(r_s) S_s J_q(r_s)^H exp(2 pi i b . r_s / lambda),

    S_s = [[I + Q, U - iV],
           [U + iV, I - Q]]     on the sky basis (e_N, e_E) of source s,

in mmflow's ``avg`` normalisation (an unpolarised source of flux I gives ``V_xx = |J_x|^2 I``)
and the IAU convention: Q > 0 is a north-south electric field, the polarisation angle
``chi = atan2(U, Q) / 2`` runs from north through east, V > 0 is the field turning from north
through east as the receiver sees it (:func:`mmflow.conventions.stokes_coherency`, the one
definition the imager's kernels use too; the sign of V follows from the fringe's time
dependence, docs/conventions.md). ``e_N`` is the unit tangent towards the celestial pole of
date and ``e_E = e_N x r`` (towards increasing RA); both are derived here from their definition.

This module is the independent check of :mod:`mmflow.mmode.polarised`: it shares only the
Jones beam evaluation (:meth:`mmflow.telescope.jones.JonesBeam.jones_enu`, ENU vectors) and
the sidereal geometry of :mod:`mmflow.conventions` with it, none of its harmonic code.

Evaluation. With the antenna phasors ``z_as = exp(2 pi i x_a . r_s / lambda)`` and
``A[(a, p), (s, c)] = conj(z_as) J_pc(r_s)`` (``c`` in N, E), all baselines and feed pairs of
one integration are one product ``V = (A S) A^H`` with ``S`` block-diagonal over sources:
``V[(i, p), (j, q)] = sum_s conj(z_is) z_js J_p S_s J_q^H``.

Polarisation leakage (D-terms, :func:`apply_leakage`): each antenna's feeds pick up a fraction
of the other feed's voltage, ``V'_ij = D_i V_ij D_j^H`` on the feed matrix ``[[xx, xy], [yx, yy]]``
with ``D_i = [[1, d_ix], [-d_iy, 1]]``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg.blas import get_blas_funcs

from mmflow.conventions import enu_to_equatorial_matrix, stokes_coherency
from mmflow.errors import InputError
from mmflow.simulate.visibilities import auto_columns, few_pairs, thermal_noise
from mmflow.conventions import SPEED_OF_LIGHT

#: Correlations in the default order of the output's correlation axis (x east, y north).
CORRELATIONS = ("xx", "yy", "xy", "yx")
_FEED = {"x": 0, "y": 1}


@dataclass
class PolarisedPoints:
    """Point sources in the celestial frame of date with IAU Stokes ``(I, Q, U, V)`` in Jy.

    Attributes
    ----------
    vectors : ndarray (n, 3) unit vectors
    stokes_jy : ndarray (n, 4) columns I, Q, U, V
    """

    vectors: np.ndarray
    stokes_jy: np.ndarray

    def __post_init__(self):
        self.vectors = np.asarray(self.vectors, float).reshape(-1, 3)
        self.stokes_jy = np.asarray(self.stokes_jy, float).reshape(-1, 4)
        if len(self.vectors) != len(self.stokes_jy):
            raise InputError("polarised sky", "stokes_jy", f"{len(self.stokes_jy)} Stokes rows for "
                             f"{len(self.vectors)} directions", "give one (I, Q, U, V) row per source")


def north_east(vectors):
    """Celestial north ``e_N`` (towards the pole, tangent) and east ``e_E = e_N x r`` at ``vectors``.

    Undefined at the poles themselves (returns NaN there).
    """
    r = np.asarray(vectors, float)
    pole = np.array([0.0, 0.0, 1.0])
    with np.errstate(invalid="ignore", divide="ignore"):
        n = pole - r[..., 2:3] * r
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return n, np.cross(n, r)


def coherency(stokes_jy):
    """``S = [[I + Q, U - iV], [U + iV, I - Q]]`` of each source, shape ``(n, 2, 2)`` on (N, E)
    (:func:`mmflow.conventions.stokes_coherency`)."""
    return stokes_coherency(np.asarray(stokes_jy, float).reshape(-1, 4))


#: sources summed at once per integration (the product's ``(2 n_ant, 2 n_src)`` factors stay ~100 MB at 256
#: antennas: a diffuse sky's million points in pieces)
SOURCE_BLOCK = 8192


def simulate_polarised_drift_scan(telescope, jones, freq_hz, lsts, sky, pairs=None, correlations=CORRELATIONS,
                                  dterms=None, dtype=np.complex128):
    """Noise-free ``V_pq`` of every pair and correlation for each sidereal angle in ``lsts``.

    Parameters
    ----------
    telescope : mmflow.telescope.Telescope
        Antenna positions (``layout.enu``) and latitude; its scalar beam is not used.
    jones : mmflow.telescope.jones.JonesBeam
        Feeds x (east) and y (north) of every antenna.
    freq_hz : float
    lsts : array_like (n_time,)
        Sidereal angles in radians (:mod:`mmflow.conventions`).
    sky : PolarisedPoints
    pairs : ndarray (n_bl, 2), optional
        Antenna pairs ``(i, j)``; default ``telescope.antenna_pairs()``.
    correlations : sequence of str
        Feed pairs ``"pq"`` of the output's correlation axis.
    dterms : ndarray complex ``(n_ant, 2)``, optional
        Polarisation leakage ``(d_x, d_y)`` of every antenna, applied to the four correlations
        by :func:`apply_leakage` before ``correlations`` are selected; None: no leakage.
    dtype : complex128 or complex64
        Precision of the per-integration products (complex64: a diffuse sky's samples, at the SGEMM
        rate; rounding ~1e-6 of the largest visibility). Sources are summed :data:`SOURCE_BLOCK` at a
        time; an unpolarised sky (``S_s = I_s 1``) as ``sum_s I_s A_s A_s^H``, Hermitian rank-k updates of
        ``sqrt(|I_s|) A_s`` (``herk``, sign by sign: half the product's flops).

    Returns
    -------
    ndarray complex128 ``(n_time, n_corr, n_bl)`` in Jy.
    """
    if dterms is not None:
        full = simulate_polarised_drift_scan(telescope, jones, freq_hz, lsts, sky, pairs, dtype=dtype)
        full = apply_leakage(full, telescope.antenna_pairs() if pairs is None else pairs, dterms)
        return full[:, [CORRELATIONS.index(c) for c in correlations]]
    pairs = telescope.antenna_pairs() if pairs is None else np.asarray(pairs)
    lsts = np.atleast_1d(np.asarray(lsts, float))
    x_wl = telescope.layout.enu * (freq_hz / SPEED_OF_LIGHT)  # (n_ant, 3) wavelengths
    e_n, e_e = north_east(sky.vectors)  # celestial frame, (n_src, 3)
    s_mat = coherency(sky.stokes_jy)  # (n_src, 2, 2)
    p_idx = np.array([_FEED[c[0]] for c in correlations])
    q_idx = np.array([_FEED[c[1]] for c in correlations])
    out = np.zeros((len(lsts), len(correlations), len(pairs)), np.complex128)
    n_ant = len(x_wl)

    def blocks(phi):  # the sources above the horizon at phi, SOURCE_BLOCK at a time, with their feed responses
        rot = enu_to_equatorial_matrix(telescope.lat_rad, phi)  # r_eq = rot @ r_enu
        r_all = sky.vectors @ rot
        up_all = np.flatnonzero(r_all[:, 2] > 0)
        for s0 in range(0, len(up_all), SOURCE_BLOCK):
            up = up_all[s0:s0 + SOURCE_BLOCK]
            yield up, _feeds(jones, freq_hz, rot, r_all[up], up, x_wl, e_n, e_e).astype(dtype, copy=False)

    if few_pairs(pairs, n_ant):  # a corner turn's chunk: the feeds of the baselines' two ends only
        return _correlate_pairs(blocks, lsts, pairs, s_mat, p_idx, q_idx, dtype, out)
    unpolarised = not np.any(sky.stokes_jy[:, 1:])
    herk = get_blas_funcs("herk", dtype=np.dtype(dtype))
    feed_rows = 2 * pairs[None, :, 0] + p_idx[:, None]  # (corr, bl): V_(ip),(jq) of the 2N x 2N feed matrix
    feed_cols = 2 * pairs[None, :, 1] + q_idx[:, None]
    lower = feed_rows > feed_cols  # herk writes the upper triangle: there V_rc = conj(V_cr)
    full_at = feed_cols * (2 * n_ant) + feed_rows  # positions in the (Fortran-ordered) matrix's memory
    upper_at = np.where(lower, feed_rows * (2 * n_ant) + feed_cols, full_at)
    for t, phi in enumerate(lsts):
        vis = None
        for up, a in blocks(phi):
            if vis is None:
                vis = np.zeros((2 * n_ant, 2 * n_ant), dtype, order="F")
            n_up = len(up)
            if unpolarised:  # S_s = I_s 1: sum_s I_s A_s A_s^H, the upper triangle by herk of each sign
                flux = sky.stokes_jy[up, 0]
                for sign in (1.0, -1.0):
                    cols = np.flatnonzero(sign * flux > 0)
                    if len(cols):
                        b_s = a[:, :, cols] * np.sqrt(np.abs(flux[cols]))[None, None, :, None].astype(a.real.dtype)
                        vis = herk(sign, b_s.reshape(2 * n_ant, 2 * len(cols)), beta=1.0, c=vis, overwrite_c=True)
                continue
            a_s = np.einsum("apsc,scd->apsd", a, s_mat[up].astype(dtype, copy=False))
            vis += a_s.reshape(2 * n_ant, 2 * n_up) @ a.reshape(2 * n_ant, 2 * n_up).conj().T
        if vis is None:  # no source above the horizon
            continue
        out[t] = np.take(vis.ravel(order="F"), upper_at if unpolarised else full_at)  # one gather, in memory order
        if unpolarised:
            np.conjugate(out[t], out=out[t], where=lower)
    return out


def _feeds(jones, freq_hz, rot, r_enu, up, x_wl, e_n, e_e):
    """Feed responses ``A_s`` of every antenna to the sources ``up`` (ENU directions ``r_enu``, frame rotation
    ``rot``): ``conj(z_as) J_p(r_s)`` on the sky basis (north, east), ``(ant, feed, src, [N, E])``."""
    j_enu = jones.jones_enu(r_enu, freq_hz)  # (feed, 3, n_up)
    basis = np.stack([e_n[up] @ rot, e_e[up] @ rot], axis=1)  # (n_up, [N, E], 3) in ENU
    j_ne = np.einsum("pis,sci->psc", j_enu, basis)  # (feed, n_up, [N, E])
    z = np.exp(2j * np.pi * (x_wl @ r_enu.T))  # (n_ant, n_up)
    return np.conj(z)[:, None, :, None] * j_ne[None]


def _correlate_pairs(blocks, lsts, pairs, s_mat, p_idx, q_idx, dtype, out):
    """:func:`simulate_polarised_drift_scan` for a few baselines of a large array
    (:func:`mmflow.simulate.visibilities.few_pairs`): per integration ``V_AB = sum_s A_s[A] S_s A_s[B]^H`` between
    the feeds of the antennas ``A`` at the baselines' first ends and ``B`` at their second (one GEMM,
    ``2|A| x 2|B|``), instead of the ``2N x 2N`` feed matrix of the whole array: a corner turn's 256 baselines at
    256 antennas (one or two first antennas) need ``|A| |B| << N^2`` of its entries. ``blocks(phi)``: the
    sources above the horizon and their feed responses, as the full path takes them. The same values to rounding
    (``tests/unit/simulate/test_polarised.py``); each integration's product is its own."""
    ant_a, ea = np.unique(pairs[:, 0], return_inverse=True)
    ant_b, eb = np.unique(pairs[:, 1], return_inverse=True)
    rows, cols = 2 * ea.ravel()[None, :] + p_idx[:, None], 2 * eb.ravel()[None, :] + q_idx[:, None]  # (corr, bl)
    for t, phi in enumerate(lsts):
        v = np.zeros((2 * len(ant_a), 2 * len(ant_b)), dtype)
        for up, a in blocks(phi):
            a_s = np.einsum("apsc,scd->apsd", a[ant_a], s_mat[up].astype(dtype, copy=False))
            v += a_s.reshape(2 * len(ant_a), 2 * len(up)) @ a[ant_b].reshape(2 * len(ant_b), 2 * len(up)).conj().T
        out[t] = v[rows, cols]
    return out


def apply_leakage(vis, pairs, dterms, correlations=CORRELATIONS):
    """Corrupt the four linear correlations with per-antenna polarisation leakage (D-terms).

    Feed p of antenna i records ``v'_ip = sum_p' D_i[p, p'] v_ip'`` with::

        D_i = [[1,      d_ix],      (rows and columns: feeds x east, y north)
               [-d_iy,  1   ]],

    so on the feed matrix of each pair ``V_ij = [[xx, xy], [yx, yy]]`` (``V_ij[p, q] =
    <v_ip conj(v_jq)>``)::

        V'_ij = D_i V_ij D_j^H,   e.g.  xx' = xx + conj(d_jx) xy + d_ix yx + d_ix conj(d_jx) yy,
                                        xy' = xy + d_ix yy - conj(d_jy) xx - d_ix conj(d_jy) yx.

    The linear-feed form with the minus sign (MeqTrees' leakage Jones ``[[1, d], [-d, 1]]`` for
    ``d_x = d_y``): a rotation of both dipoles by a small angle ``theta`` (x towards y, east
    towards north) is ``d_x = d_y = theta`` to first order, and leaves ``xx + yy`` unchanged but
    for the factor ``1 + theta^2``. CASA's D Jones (``DJones::calcOneJones``) is
    ``[[1, d_0], [d_1, 1]]``: its ``d_0`` is ``d_x``, its ``d_1`` is ``-d_y`` here.

    Parameters
    ----------
    vis : ndarray complex ``(..., n_corr, n_bl)``
        Visibilities as :func:`simulate_polarised_drift_scan` returns them (``(n_time, n_corr,
        n_bl)``); ``correlations`` must hold xx, yy, xy and yx.
    pairs : ndarray ``(n_bl, 2)``
        Antenna indices ``(i, j)`` of each baseline.
    dterms : ndarray complex ``(n_ant, 2)``
        ``(d_x, d_y)`` of every antenna.
    correlations : sequence of str
        The correlations on ``vis``'s correlation axis.

    Returns
    -------
    ndarray complex128, the shape of ``vis``.
    """
    if sorted(correlations) != sorted(CORRELATIONS):
        raise InputError("polarisation leakage", "correlations", f"{tuple(correlations)}",
                         "give all four correlations xx, yy, xy, yx: leakage mixes them")
    vis = np.asarray(vis, np.complex128)
    pairs = np.asarray(pairs).reshape(-1, 2)
    d = np.asarray(dterms, np.complex128).reshape(-1, 2)
    jones = np.ones((len(d), 2, 2), np.complex128)
    jones[:, 0, 1], jones[:, 1, 0] = d[:, 0], -d[:, 1]
    p_idx = [_FEED[c[0]] for c in correlations]
    q_idx = [_FEED[c[1]] for c in correlations]
    mat = np.zeros(vis.shape[:-2] + (vis.shape[-1], 2, 2), np.complex128)  # (..., n_bl, p, q)
    mat[..., p_idx, q_idx] = np.moveaxis(vis, -2, -1)
    out = np.einsum("bpr,...brs,bqs->...bpq", jones[pairs[:, 0]], mat, jones[pairs[:, 1]].conj())
    return np.moveaxis(out[..., p_idx, q_idx], -1, -2)


def correlation_noise(vis, pairs, bandwidth_hz, integration_s, rng):
    """Add radiometer noise to the four correlations ``(time, baseline, [xx, yy, xy, yx])`` in place.

    ``sigma_pq^2 = V_ii^pp V_jj^qq / (dnu tau)`` for feed p of antenna i and feed q of antenna j
    (:func:`mmflow.simulate.visibilities.thermal_noise`, from the autocorrelations in ``vis`` before the
    noise): complex on every correlation, real on the parallel hands' autocorrelations, and an
    autocorrelation's yx is conj(xy), one draw for the pair, as in any correlator. Returns ``vis``.
    """
    is_auto, ci, cj = auto_columns(np.asarray(pairs))
    autos = {feed: np.real(vis[:, is_auto, CORRELATIONS.index(feed * 2)]) for feed in "xy"}
    for c, (p, q) in enumerate(CORRELATIONS):
        noise, _ = thermal_noise(vis[..., c], autos[p][:, ci], autos[q][:, cj], bandwidth_hz, integration_s, rng,
                                 is_auto if p == q else None)
        vis[..., c] += noise
    vis[:, is_auto, CORRELATIONS.index("yx")] = np.conj(vis[:, is_auto, CORRELATIONS.index("xy")])
    return vis
