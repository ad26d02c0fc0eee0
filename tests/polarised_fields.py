"""Four-correlation visibilities of polarised point sources from real electric fields in the time domain.

Independent of mmflow's simulator, coherency and Stokes conventions (used by
tests/unit/imaging/test_stokes_sign.py and tests/unit/test_polarised_defaults.py). A source of IAU
Stokes ``(I, Q, U, V)`` is a fully polarised part of intensity ``P = sqrt(Q^2 + U^2 + V^2)``,
an ellipse::

    E(t) = sqrt(2 P) [cos(beta) cos(w t) u + sin(beta) sin(w t) v],
    u = cos(chi) e_N + sin(chi) e_E,   v = -sin(chi) e_N + cos(chi) e_E,
    chi = atan2(U, Q) / 2 (north through east),   sin(2 beta) = V / P,

(V > 0: the vector turns from ``u`` towards ``v``, i.e. from north through east as the receiver,
looking at the source, sees it: IAU), plus ``I - P`` unpolarised: two incoherent linear fields
along ``e_N`` and ``e_E`` of amplitude ``sqrt(I - P)``. Each part is delayed to each antenna
(``E(x, t) = E(t + x . r / c)``: the wavefront reaches the antenna nearer the source first),
projected on short dipoles x (east) and y (north), and channelised by ``2 <v(t) exp(+i w t)>``,
the DFT sign that gives mmflow's fringe (``<v_i v_j*>`` as ``exp(+2 pi i (x_j - x_i) . r /
lambda)``); the parts' correlations add. What it takes from mmflow is the sidereal geometry
(:func:`mmflow.conventions.enu_to_equatorial_matrix`) and the speed of light.
"""
import numpy as np

from mmflow.conventions import enu_to_equatorial_matrix
from mmflow.conventions import SPEED_OF_LIGHT

N_SAMPLES = 16  # samples of one period: the DFT of a sinusoid is exact for >= 3
TAPER = 3.0  # the dipoles' cos(za)^TAPER horizon taper (as ShortDipoleJones(horizon_taper=3))
#: correlations [xx, yy, xy, yx] as feed pairs (x = 0 east, y = 1 north)
CORR = ((0, 0), (1, 1), (0, 1), (1, 0))


def north_east_enu(r_eq, rot):
    """Celestial north (towards the pole, tangent) and east (``north x r``, towards increasing RA)
    at the direction ``r_eq`` (celestial frame), as ENU vectors with ``r_eq = rot @ r_enu``."""
    pole = np.array([0.0, 0.0, 1.0])
    n = pole - r_eq[2] * r_eq
    n /= np.linalg.norm(n)
    return n @ rot, np.cross(n, r_eq) @ rot


def field_parts(stokes, e_n, e_e, wt):
    """The real fields ``(3,) + wt.shape`` of a source's incoherent parts at phases ``wt = w t``."""
    i, q, u, v = np.asarray(stokes, float)
    p = float(np.sqrt(q * q + u * u + v * v))
    parts = []
    if p > 0:
        chi, beta = 0.5 * np.arctan2(u, q), 0.5 * np.arcsin(np.clip(v / p, -1, 1))
        uu = np.cos(chi) * e_n + np.sin(chi) * e_e
        vv = -np.sin(chi) * e_n + np.cos(chi) * e_e
        a = np.sqrt(2 * p)
        parts.append(
            a * (np.cos(beta) * np.multiply.outer(uu, np.cos(wt)) + np.sin(beta) * np.multiply.outer(vv, np.sin(wt)))
        )
    if i - p > 1e-15 * i:
        parts += [np.sqrt(i - p) * np.multiply.outer(e, np.cos(wt)) for e in (e_n, e_e)]
    return parts


def dipoles(r_enu):
    """Short dipoles along east (x) and north (y), ``d - (d . r) r``, times ``cos(za)^TAPER``: (2, 3)."""
    d = np.eye(3)[:2]
    return (d - np.outer(d @ r_enu, r_enu)) * r_enu[2] ** TAPER


def channel(v, wt):
    """Complex amplitude of the real voltages ``v (..., n_t)`` at ``w``: ``2 <v exp(+i w t)>`` over one period."""
    return 2 * np.mean(v * np.exp(1j * wt), axis=-1)


def correlate(layout_enu, freq_hz, lat_rad, lsts, sources, pairs):
    """``V_pq`` of every pair (i, j) and correlation [xx, yy, xy, yx] for each LST: ``(n_t, 4, n_bl)``.

    ``sources``: ``[(stokes (I, Q, U, V) Jy, unit vector in the celestial frame of date), ...]``.
    """
    w = 2 * np.pi * freq_hz
    wt = 2 * np.pi * np.arange(N_SAMPLES) / N_SAMPLES
    pairs = np.asarray(pairs)
    out = np.zeros((len(lsts), 4, len(pairs)), complex)
    for t, phi in enumerate(lsts):
        rot = enu_to_equatorial_matrix(lat_rad, phi)
        for stokes, r_eq in sources:
            r = r_eq @ rot
            if r[2] <= 0:
                continue
            e_n, e_e = north_east_enu(r_eq, rot)
            phase = wt[None, :] + w * (layout_enu @ r / SPEED_OF_LIGHT)[:, None]  # (ant, n_t): E(x, t) = E(t + x.r / c)
            for fld in field_parts(stokes, e_n, e_e, phase):  # (3, ant, n_t)
                volt = channel(np.einsum("pk,kat->apt", dipoles(r), fld), wt)  # (ant, feed)
                for c, (p, q) in enumerate(CORR):
                    out[t, c] += volt[pairs[:, 0], p] * np.conj(volt[pairs[:, 1], q])
    return out
