"""Polarisation leakage (D-terms) of a simulated array, imaged without polarisation calibration
(issue 22: "the leakage terms of a simulated array must not break the imaging of I").

The scene of tests/polarised_scene.py (20 antennas, 300 integrations, lmax 32); each antenna's
feeds leak ``D_i = [[1, d_ix], [-d_iy, 1]]`` (:func:`mmflow.simulate.polarised.apply_leakage`)
with ``|d|`` uniform in 1-5 % and random phases (fixed seed), typical of a dipole array. Data
with and without D-terms are imaged through the same operators (the full-Stokes solve, and the
Stokes-I engine on ``(xx + yy) / 2``), so a map difference is the D-terms' effect alone.

First order in d, for an unpolarised source seen at the zenith (``xx = yy = I``,
``xy = yx = 0``): ``xy' = (d_ix - conj(d_jy)) I``, ``yx' = (conj(d_jx) - d_iy) I``, i.e. in the
feed frame ``U = Re <d_x - d_y> I``, ``V = -Im <d_x + d_y> I`` (``<>``: the array mean; the
antenna-to-antenna scatter is not a sky and is imaged like noise) and ``Q = 0``. V does not
depend on the frame: the V leak of the array-mean D-terms is that V imaged through the same
operator.
"""
import numpy as np
import pytest

from mmflow.errors import InputError
from mmflow.simulate.polarised import CORRELATIONS, PolarisedPoints, apply_leakage, simulate_polarised_drift_scan
from mmflow.telescope import Telescope
from mmflow.telescope.jones import ShortDipoleJones
from tests.polarised_scene import FREQ, POL_FRAC, POL_I, POL_RADEC, radec_vectors, scene_layout

THETA = 0.03  # a common feed rotation of 0.03 rad


def test_apply_leakage_is_the_jones_product_per_baseline():
    """``V'_ij = D_i V_ij D_j^H`` per baseline (autocorrelations and both orders of a pair), in any
    order of the correlation axis; a common small rotation (``d_x = d_y = theta``) scales
    ``xx + yy`` by ``1 + theta^2`` exactly; the simulator's ``dterms`` is the same corruption."""
    rng = np.random.default_rng(0)
    n_ant, n_t = 5, 3
    pairs = np.array([[0, 0], [0, 1], [1, 0], [1, 3], [2, 4], [4, 4]])
    vis = rng.normal(size=(n_t, 4, len(pairs))) + 1j * rng.normal(size=(n_t, 4, len(pairs)))
    d = 0.05 * (rng.normal(size=(n_ant, 2)) + 1j * rng.normal(size=(n_ant, 2)))
    got = apply_leakage(vis, pairs, d)
    for t in range(n_t):
        for k, (i, j) in enumerate(pairs):
            v = np.array([[vis[t, 0, k], vis[t, 2, k]], [vis[t, 3, k], vis[t, 1, k]]])  # [[xx, xy], [yx, yy]]
            di, dj = (np.array([[1, d[a, 0]], [-d[a, 1], 1]]) for a in (i, j))
            want = di @ v @ dj.conj().T
            np.testing.assert_allclose(got[t, :, k], [want[0, 0], want[1, 1], want[0, 1], want[1, 0]], atol=1e-14)
    order = [3, 0, 2, 1]  # yx, xx, xy, yy
    np.testing.assert_allclose(apply_leakage(vis[:, order], pairs, d, [CORRELATIONS[c] for c in order]),
                               got[:, order], atol=1e-14)
    rot = apply_leakage(vis, pairs, np.full((n_ant, 2), THETA))
    np.testing.assert_allclose(rot[:, 0] + rot[:, 1], (1 + THETA ** 2) * (vis[:, 0] + vis[:, 1]), atol=1e-13)
    with pytest.raises(InputError):
        apply_leakage(vis[:, :2], pairs, d, ("xx", "yy"))
    jones = ShortDipoleJones(horizon_taper=3.0)
    tel = Telescope(scene_layout(6, 6.0), jones.power_beam(), [FREQ])
    sky = PolarisedPoints(radec_vectors(POL_RADEC), np.c_[POL_I, POL_I[:, None] * POL_FRAC])
    lst = np.linspace(0, 2 * np.pi, 7)
    d6 = 0.03 * np.exp(2j * np.pi * rng.uniform(size=(6, 2)))
    full = apply_leakage(simulate_polarised_drift_scan(tel, jones, FREQ, lst, sky), tel.antenna_pairs(), d6)
    np.testing.assert_allclose(simulate_polarised_drift_scan(tel, jones, FREQ, lst, sky, correlations=("yy", "xy"),
                                                             dterms=d6), full[:, [1, 2]], atol=1e-12)
