"""Full-Stokes transfer coefficients: the four linear correlations' response to T, E, B and V.

Sky (IAU convention). At each direction the polarisation basis is ``(e_N, e_E) =
(-e_theta, e_phi)`` of the celestial frame (north, east on the sky); Stokes Q is positive
for an electric field along north-south and the polarisation angle is measured from north
through east. The sky's coherency on that basis, normalised as mmflow's ``avg`` convention
(an unpolarised sky gives ``V_xx = V_yy = I`` through unit feeds), is::

    S = <E E^H> = [[I + Q, U - iV],
                   [U + iV, I - Q]]       (:func:`mmflow.conventions.stokes_coherency`)

(V > 0: the field turning from north through east as the receiver sees it; with this fringe,
``exp(+2 pi i b . r)``, the fields are ``Re[A exp(-i w t)]``, the conjugate of Hamaker & Bregman's
``XY = U + iV`` for X north under ``exp(-2 pi i b . r)``: docs/conventions.md).

Correlation pq of baseline ``b = x_j - x_i`` (wavelengths, sky frame at ``phi = 0``), feed p
of antenna i and q of antenna j, with ``J_p = (J_pN, J_pE)`` the feed's response on that basis
(:mod:`mmflow.telescope.jones`) and ``f_b = exp(2 pi i b . r)``::

    V_pq = int f_b J_p S J_q^H dOmega = int f_b (K_I I + K_Q Q + K_U U + K_V V) dOmega,
    K_I = J_pN J_qN^* + J_pE J_qE^*,    K_Q = J_pN J_qN^* - J_pE J_qE^*,
    K_U = J_pN J_qE^* + J_pE J_qN^*,    K_V = -i (J_pN J_qE^* - J_pE J_qN^*),

i.e. ``K_X = sum_ab sigma_X[a, b] J_pa J_qb^*`` with ``sigma_X`` of :data:`mmflow.conventions.STOKES_COHERENCY`.

Harmonics. I and V are spin 0: ``I = sum T_lm Y_lm``, ``V = sum V_lm Y_lm``. Q and U go
through healpy's spin-2 convention, which is the COSMO one (``U_h = -U``):
``Q + i U_h = sum a_{2,lm} 2Y_lm``, ``Q - i U_h = sum a_{-2,lm} -2Y_lm``,
``a_{+-2} = -(E_lm +- i B_lm)``. With ``h_+- = f_b (K_Q +- i K_U) / 2`` (so that
``K_Q Q + K_U U = h_+ (Q + iU_h) + h_- (Q - iU_h)`` up to ``f_b``)::

    b^T_lm = int f_b K_I Y_lm,      b^V_lm = int f_b K_V Y_lm,
    b^E_lm = -(int h_+ 2Y_lm + int h_- -2Y_lm),   b^B_lm = -i (int h_+ 2Y_lm - int h_- -2Y_lm),

(harmonics *not* conjugated, as in :mod:`mmflow.mmode.transfer`) and, for every m,
``V_pq,m = sum_X sum_l b^X_lm X_lm`` with ``X_{l,-m} = (-1)^m conj(X_lm)`` (real fields), the
sky rotating under the array as in the Stokes-I path (z rotations keep ``(e_N, e_E)``, so
Q and U rotate as scalars). The stored ``-m`` row (``conj(V_{-m})``, the layout of
:mod:`mmflow.conventions`) is ``c^X_lm = (-1)^m conj(b^X_{l,-m})``; it equals the ``+m`` row
of correlation qp of the reversed baseline. For an unpolarised sky and the Stokes-I power
beam ``A_I = (|J_x|^2 + |J_y|^2) / 2``, ``(b^{xx,T} + b^{yy,T}) / 2`` is the Stokes-I ``B_lm``.

Quadrature. The integrals are exact weighted sums on a Gauss-Legendre grid exact to
``lmax + L_f`` (as the Stokes-I path), taken by ducc0's adjoint spin-0 / spin-2 transforms
of the weighted kernel maps: for a complex map g, ``int g sY_lm = conj(int g^* sY_lm^*)``,
and the transforms of real maps give every m through the reality relations.
These are the reference kernels (six transforms per baseline and correlation), the independent
computation the fast path is tested against: :mod:`mmflow.mmode.polarised_transfer` computes the
same coefficients by ring FFTs and per-m GEMMs, as the Stokes-I path does.
"""
from __future__ import annotations

from dataclasses import dataclass

import ducc0
import numpy as np

from mmflow.conventions import STOKES_COHERENCY, enu_to_azza, enu_to_equatorial_matrix, unit_vectors
from mmflow.mmode.transfer import QuadratureGrid

#: Stokes parameters of the transfer coefficients, in the order of their axis.
STOKES = ("T", "E", "B", "V")
#: Correlations, in the order of their axis by default.
CORRELATIONS = ("xx", "yy", "xy", "yx")
_FEED = {"x": 0, "y": 1}


@dataclass
class PolarisedGrid(QuadratureGrid):
    """A :class:`~mmflow.mmode.transfer.QuadratureGrid` (its ``weights`` include ``2 pi / n_phi``)
    with the feeds' responses on ``(e_N, e_E)``.

    Attributes
    ----------
    jn, je : ndarray complex (2, n_theta, n_phi): ``J_p . e_N`` and ``J_p . e_E`` for feeds x, y
    """

    jn: np.ndarray
    je: np.ndarray


def feed_projections(jones, lat_rad, vectors, freq_hz, phi=0.0):
    """``(J_pN, J_pE)``: the feeds' responses on the sky basis at directions ``vectors``.

    ``J_p = J_ptheta e_theta + J_pphi e_phi`` (ENU, :meth:`mmflow.telescope.jones.JonesBeam.jones`) with the
    array at sidereal angle ``phi``, projected on celestial north ``e_N = -e_theta`` and east ``e_E = e_phi``:
    ``J_pN = J_ptheta (e_theta . e_N) + J_pphi (e_phi . e_N)``, likewise ``J_pE``. The four real overlaps
    (a rotation by the parallactic angle) are formed component by component in ENU, ``e_N`` and ``e_E``
    taken there by ``M^T`` (:func:`mmflow.conventions.enu_to_equatorial_matrix`); the same as rotating
    :meth:`~mmflow.telescope.jones.JonesBeam.jones_enu` to the celestial frame and projecting it, to
    rounding, without complex 3-vectors (1.5-2.5x faster a grid: 1,002 x 2,016 points 1.1-3.5 -> 0.7-1.4 s,
    one thread, a noisy VM).

    Returns
    -------
    jn, je : complex (2,) + vectors.shape[:-1]
    """
    mat = enu_to_equatorial_matrix(lat_rad, phi)
    vectors = np.asarray(vectors, float)
    enu = vectors @ mat
    comp = jones.jones(*enu_to_azza(enu), freq_hz)  # (feed, (theta, phi), ...)
    sa, ca, sz, cz = _sin_cos(enu[..., 0], enu[..., 1]) + (enu[..., 2],)  # of az (north through east), za
    del enu
    sp, cp, st, ct = _sin_cos(vectors[..., 1], vectors[..., 0]) + (vectors[..., 2],)  # of phi, theta
    # e_N = -(ct cp, ct sp, -st), e_E = (-sp, cp, 0) in the celestial frame; ENU component i is sum_k e_k M[k, i]
    north = [-(ct * cp * mat[0, i] + ct * sp * mat[1, i] - st * mat[2, i]) for i in range(3)]
    east = [-sp * mat[0, i] + cp * mat[1, i] for i in range(3)]
    out = []
    for e in (north, east):  # e_theta = (cz sa, cz ca, -sz), e_phi = (-ca, sa, 0) in ENU
        on_theta = cz * sa * e[0] + cz * ca * e[1] - sz * e[2]
        on_phi = sa * e[1] - ca * e[0]
        out.append(comp[:, 0] * on_theta + comp[:, 1] * on_phi)
    return out[0], out[1]


def _sin_cos(y, x):
    """``(sin a, cos a, r)`` of ``a = arctan2(y, x)``, ``r = hypot(x, y)``, without the angle: for unit vectors
    ``r`` is the sine of the polar angle; at ``r = 0`` the angle is 0, as ``arctan2`` gives it."""
    r = np.hypot(x, y)
    pole = r == 0
    safe = np.where(pole, 1.0, r)
    return np.where(pole, 0.0, y / safe), np.where(pole, 1.0, x / safe), r


def stokes_kernels(jn, je, corr):
    """``(K_I, K_Q, K_U, K_V)`` of correlation ``corr`` (e.g. ``"xy"``): ``J_p S J_q^H`` per Stokes,
    ``K_X = sum_ab sigma_X[a, b] J_pa J_qb^*`` on ``(a, b) in (N, E)`` with the coherency of unit
    Stokes X, ``sigma_X`` (:data:`mmflow.conventions.STOKES_COHERENCY`, the simulator's too)."""
    p, q = _FEED[corr[0]], _FEED[corr[1]]
    jp = np.stack([jn[p], je[p]])
    jq = np.conj(np.stack([jn[q], je[q]]))
    outer = jp[:, None] * jq[None, :]  # [a, b, ...] = J_pa J_qb^*
    return tuple(np.tensordot(STOKES_COHERENCY, outer, axes=([1, 2], [0, 1])))


def make_polarised_grid(lat_rad, jones, freq_hz, lmax, fringe_lmax):
    """Grid exact to ``lmax + fringe_lmax`` with the feeds on it.

    The rings and ``n_phi`` are those of :func:`mmflow.mmode.transfer.make_grid` (the same
    quadrature as the Stokes-I path), with ``n_phi >= 2 lmax + 2`` for the transforms.
    """
    quad = lmax + fringe_lmax
    n_theta = quad // 2 + 2
    n_theta += n_theta % 2
    n_phi = ducc0.fft.good_size(max(quad + 2, 2 * lmax + 2))
    theta = ducc0.misc.GL_thetas(n_theta)
    weights = ducc0.misc.GL_weights(n_theta, n_phi)
    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    vec = unit_vectors(theta[:, None], phi[None, :])
    jn, je = feed_projections(jones, lat_rad, vec, freq_hz)
    return PolarisedGrid(lmax, quad, theta, weights, n_phi, vec, jn, je)


def _adjoint(grid, maps, spin):
    """``sum_k w_k maps_k sY_lm^*`` (healpy layout, m >= 0) of real maps ``(ncomp, n_theta, n_phi)``."""
    weighted = np.ascontiguousarray(maps * grid.weights[None, :, None])
    return ducc0.sht.experimental.adjoint_synthesis_2d(map=weighted, spin=spin, lmax=grid.lmax, geometry="GL")


def _unpack(grid, alm):
    """healpy-layout ``alm`` (m >= 0) as ``(lmax + 1, lmax + 1)`` ``[l, m]`` (zero for m > l)."""
    L = grid.lmax
    out = np.zeros((L + 1, L + 1), complex)
    i = 0
    for m in range(L + 1):
        out[m:, m] = alm[i:i + L + 1 - m]
        i += L + 1 - m
    return out


def _all_m(pos, neg_source):
    """Assemble ``[l, lmax + m]`` for ``m = -lmax..lmax`` from ``pos[l, m]`` (m >= 0) and
    ``neg[l, k]`` giving the ``m = -k`` entries (``k >= 1``)."""
    L = pos.shape[0] - 1
    out = np.zeros((L + 1, 2 * L + 1), complex)
    out[:, L:] = pos
    out[:, :L] = neg_source[:, 1:][:, ::-1]
    return out


def _sign_m(L):
    return (-1.0) ** np.arange(L + 1)[None, :]


def spin0_integrals(grid, g):
    """``int g Y_lm dOmega`` for a complex map g, ``[l, lmax + m]``, ``m = -lmax..lmax``.

    For real ``h``, ``A_lm = int h Y_lm^*`` gives ``int h Y_lm = conj(A_lm)`` and
    ``int h Y_{l,-m} = (-1)^m A_lm``; ``g = h_r + i h_i`` by linearity.
    """
    a = [_unpack(grid, _adjoint(grid, part[None], 0)[0]) for part in (g.real, g.imag)]
    pos = np.conj(a[0]) + 1j * np.conj(a[1])
    neg = _sign_m(grid.lmax) * (a[0] + 1j * a[1])
    return _all_m(pos, neg)


def spin2_integrals(grid, g, spin):
    """``int g sY_lm dOmega`` for ``spin = +2`` or ``-2`` and a complex map g, ``[l, lmax + m]``.

    For real (Q, U) the spin-2 transform gives ``(E, B)`` with ``a_{+-2,lm} = int (Q +- iU)
    +-2Y_lm^* = -(E +- i B)`` and ``a_{+-2,l,-m} = (-1)^m conj(a_{-+2,lm})``. Then
    ``int g 2Y_lm = conj(a_2[Q = Re g, U = -Im g])`` and ``int g -2Y_lm = conj(a_{-2}[Re g, Im g])``.
    """
    u = -g.imag if spin == 2 else g.imag
    e, b = (_unpack(grid, x) for x in _adjoint(grid, np.stack([g.real, u]), 2))
    a_plus, a_minus = -(e + 1j * b), -(e - 1j * b)
    sgn = _sign_m(grid.lmax)
    if spin == 2:
        full = _all_m(a_plus, sgn * np.conj(a_minus))
    else:
        full = _all_m(a_minus, sgn * np.conj(a_plus))
    return np.conj(full)


def polarised_coefficients(grid, b_wavelengths, corr):
    """``b^X_lm`` of one baseline and correlation for X in (T, E, B, V), every m.

    Parameters
    ----------
    grid : PolarisedGrid
    b_wavelengths : (3,) baseline in the sky frame at ``phi = 0``, in wavelengths
    corr : str, one of :data:`CORRELATIONS`

    Returns
    -------
    ndarray complex ``(4, lmax + 1, 2 lmax + 1)``: ``[X, l, lmax + m]`` (zero for ``|m| > l``,
    and for E, B at ``l < 2``).
    """
    fringe = np.exp(2j * np.pi * (grid.vectors @ np.asarray(b_wavelengths, float)))
    k_i, k_q, k_u, k_v = stokes_kernels(grid.jn, grid.je, corr)
    s_plus = spin2_integrals(grid, fringe * (k_q + 1j * k_u) / 2, 2)
    s_minus = spin2_integrals(grid, fringe * (k_q - 1j * k_u) / 2, -2)
    return np.stack([spin0_integrals(grid, fringe * k_i), -(s_plus + s_minus),
                     -1j * (s_plus - s_minus), spin0_integrals(grid, fringe * k_v)])


def reference_transfer_blocks(grid, b_wavelengths, correlations=CORRELATIONS):
    """Full-Stokes transfer blocks in the Stokes-I path's row layout, one per m, by the reference kernels
    (:func:`mmflow.mmode.polarised_transfer.polarised_transfer_blocks` is the fast path).

    Returns
    -------
    list over ``m = 0..lmax`` of complex arrays ``(n_corr, 4, rows, lmax - m + 1)``: axis 1 is
    :data:`STOKES`; rows ``0..n_b-1`` are ``V_m`` (coefficients ``b^X_lm``) and, for ``m > 0``,
    rows ``n_b..2n_b-1`` are ``conj(V_{-m})`` (``(-1)^m conj(b^X_{l,-m})``); columns ``l = m..lmax``.
    """
    b = np.asarray(b_wavelengths, float).reshape(-1, 3)
    L = grid.lmax
    coef = np.stack([np.stack([polarised_coefficients(grid, bb, c) for bb in b], axis=1)
                     for c in correlations])  # (corr, X, nb, l, lmax + m)
    blocks = []
    for m in range(L + 1):
        plus = coef[:, :, :, m:, L + m]
        if m == 0:
            blocks.append(np.ascontiguousarray(plus))
        else:
            minus = (-1) ** m * np.conj(coef[:, :, :, m:, L - m])
            blocks.append(np.concatenate([plus, minus], axis=2))
    return blocks
