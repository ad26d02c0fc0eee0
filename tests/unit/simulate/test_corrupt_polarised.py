"""The corruption simulator on the four linear correlations of a polarised sky (issue 22): gains per
feed, the feeds' polarisation leakage (D-terms), direction-dependent gains of bright sources,
unpolarised terrestrial signals and radiometer noise, checked against the Jones chain
``G_i (D_i [V_ij + sum_s h_si conj(h_sj) M^s_ij] D_j^H + (T_ij + S_ij) 1) G_j^H`` written out with 2 x 2 matrices
per baseline and integration (independent of the vectorised code)."""
import numpy as np
import pytest

from mmflow.simulate.corrupt import (DayCorruptions, corrupt, corrupted_visibilities, day_corruptions,
                                     direction_dependent_gains, leakage_terms)
from mmflow.simulate.polarised import CORRELATIONS, PolarisedPoints, simulate_polarised_drift_scan
from mmflow.simulate.scene import simulate_polarised_chunk
from mmflow.telescope import Telescope
from mmflow.telescope.jones import ShortDipoleJones
from tests.stokes_helpers import compact_layout

FREQ = 40e6


def _feed_matrix(v):
    """``[[xx, xy], [yx, yy]]`` of one baseline's four correlations in CORRELATIONS order."""
    return np.array([[v[0], v[2]], [v[3], v[1]]])


def _correlations(m):
    return np.array([m[0, 0], m[1, 1], m[0, 1], m[1, 0]])


@pytest.fixture(scope="module")
def scene():
    jones = ShortDipoleJones(3.0)
    tel = Telescope(compact_layout(5), jones.power_beam(), [FREQ], include_autos=True)
    tel.channel_width_hz = 24e3
    sky = PolarisedPoints(np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86]]) / np.c_[[0.9925, 1.0]],
                          np.array([[1e4, 2e3, -1e3, 5e2], [5e3, 0.0, 0.0, 0.0]]))
    sky.vectors /= np.linalg.norm(sky.vectors, axis=1, keepdims=True)
    dd = PolarisedPoints(np.array([[0.1, -0.6, 0.79]]) / np.linalg.norm([0.1, -0.6, 0.79]),
                         np.array([[2e4, 4e3, 1e3, 0.0]]))
    lsts = np.linspace(0.2, 0.9, 6)
    pairs = tel.antenna_pairs()
    n = len(tel.layout.enu)
    rng = np.random.default_rng(3)
    day = day_corruptions(n, FREQ, np.arange(12) * 60.0, 1, tel.layout.enu, rng, crosstalk_jy=50.0, leakage=0.05)
    return dict(jones=jones, tel=tel, sky=sky, dd=dd, lsts=lsts, pairs=pairs, day=day)


def test_four_correlations_follow_the_jones_chain_per_baseline(scene):
    """Per integration and baseline, the corrupted correlations equal ``G_i (D_i [V + h_i conj(h_j) M] D_j^H
    + (T_ij + S_ij) 1) G_j^H`` (S: the receiver power on the autocorrelations' xx and yy, behind the feeds,
    as the terrestrial signal T), the same chain for
    the stage's chunk (complex64), and without corruptions the uncorrupted chunk."""
    tel, jones, lsts, pairs, day = scene["tel"], scene["jones"], scene["lsts"], scene["pairs"], scene["day"]
    rows = slice(3, 3 + len(lsts))
    sky_v = np.moveaxis(simulate_polarised_drift_scan(tel, jones, FREQ, lsts, scene["sky"], pairs), 1, -1)
    dd_v = np.moveaxis(simulate_polarised_drift_scan(tel, jones, FREQ, lsts, scene["dd"], pairs), 1, -1)[None]
    vec = scene["dd"].vectors
    got = corrupted_visibilities(tel, FREQ, lsts, sky_v, dd_v, vec, day, rows, pairs, system_jy=1e5,
                                 four_correlations=True)
    h = direction_dependent_gains(tel, FREQ, lsts, vec, day.dd_offsets[:, rows], day.dd_flux[:, rows])[0]
    (pattern, amp), = day.terrestrial
    g = day.gains[rows]
    for t in range(len(lsts)):
        for b, (i, j) in enumerate(pairs):
            m = _feed_matrix(sky_v[t, b]) + h[t, i] * np.conj(h[t, j]) * _feed_matrix(dd_v[0, t, b])
            di, dj = (np.array([[1, day.dterms[a, 0]], [-day.dterms[a, 1], 1]]) for a in (i, j))
            behind = amp[rows][t] * pattern[i] * np.conj(pattern[j]) + (1e5 if i == j else 0.0)
            m = di @ m @ dj.conj().T + behind * np.eye(2)
            m = np.diag(g[t, i]) @ m @ np.diag(g[t, j]).conj()
            np.testing.assert_allclose(got[t, b], _correlations(m), rtol=1e-12, atol=1e-9)
    corrupted = [(day, [scene["dd"]], vec)]
    par, cross = simulate_polarised_chunk(tel, jones, lsts, [scene["sky"]], corrupted=corrupted, rows=rows,
                                          system_jy=1e5)
    np.testing.assert_allclose(np.concatenate([par, cross], axis=-1)[:, :, 0], got, rtol=1e-6, atol=1e-2)
    clean = DayCorruptions(None, np.zeros((0, 20, 2)), np.zeros((0, 20)), [], None)
    none = corrupted_visibilities(tel, FREQ, lsts, sky_v, np.zeros((0,) + sky_v.shape), np.zeros((0, 3)), clean,
                                  rows, pairs, four_correlations=True)
    np.testing.assert_array_equal(none, sky_v)


def test_corrupted_noise_follows_the_corrupted_autocorrelations(scene):
    """Radiometer noise after the corruptions: each correlation pq of baseline (i, j) has variance
    ``V'_ii^pp V'_jj^qq / (dnu tau)`` of the corrupted autocorrelations (system power included), real on the
    parallel hands' autocorrelations, and an autocorrelation's yx is conj(xy)."""
    tel, pairs, day = scene["tel"], scene["pairs"], scene["day"]
    n_t = 3000
    sky_v = np.repeat(np.moveaxis(simulate_polarised_drift_scan(tel, scene["jones"], FREQ, [0.4], scene["sky"], pairs),
                                  1, -1), n_t, axis=0)
    one_day = DayCorruptions(np.repeat(day.gains[:1], n_t, axis=0), np.zeros((0, n_t, 2)), np.zeros((0, n_t)), [],
                             day.dterms)
    args = (tel, FREQ, np.full(n_t, 0.4), sky_v, np.zeros((0,) + sky_v.shape), np.zeros((0, 3)), one_day,
            slice(None), pairs)
    exact = corrupted_visibilities(*args, system_jy=1e5, four_correlations=True)
    noisy = corrupted_visibilities(*args, np.random.default_rng(1), 13.0, system_jy=1e5, four_correlations=True)
    noise = noisy - exact
    auto = {int(i): exact[0, b, :2].real for b, (i, j) in enumerate(pairs) if i == j}
    for b, (i, j) in enumerate(pairs):
        for c, (p, q) in enumerate(CORRELATIONS):
            var = auto[int(i)]["xy".index(p)] * auto[int(j)]["xy".index(q)] / (24e3 * 13.0)
            assert abs(np.mean(np.abs(noise[:, b, c]) ** 2) / var - 1) < 0.1, (b, c)
            assert (np.abs(noise[:, b, c].imag).max() == 0) == (i == j and p == q), (b, c)
        if i == j:
            np.testing.assert_array_equal(noisy[:, b, 3], np.conj(noisy[:, b, 2]))


def test_leakage_is_drawn_last_and_refused_on_the_parallel_hands_alone():
    """D-terms |d| in [leakage / 5, leakage] with uniform phases, drawn after every other corruption (the
    gains and terrestrial draws are the same with and without them); the parallel hands alone cannot
    carry them."""
    enu = np.random.default_rng(0).normal(size=(40, 3))
    a = day_corruptions(40, FREQ, np.arange(5) * 60.0, 0, enu, np.random.default_rng(5), crosstalk_jy=5.0)
    b = day_corruptions(40, FREQ, np.arange(5) * 60.0, 0, enu, np.random.default_rng(5), crosstalk_jy=5.0,
                        leakage=0.04)
    assert a.dterms is None and b.dterms.shape == (40, 2)
    np.testing.assert_array_equal(a.gains, b.gains)
    np.testing.assert_array_equal(a.terrestrial[0][0], b.terrestrial[0][0])
    mag = np.abs(leakage_terms(2000, np.random.default_rng(2), 0.05))
    assert 0.01 <= mag.min() < 0.0105 and 0.0495 < mag.max() <= 0.05
    with pytest.raises(ValueError, match="four correlations"):
        corrupt(np.ones((2, 3, 2)), np.array([[0, 0], [0, 1], [1, 1]]), None, dterms=b.dterms)


def test_each_feed_sees_an_unpolarised_sky_through_its_own_power_beam():
    """A short dipole along ``d_p`` responds to an unpolarised sky with ``|J_p|^2 = (1 - (d_p . r)^2)
    cos(za)^(2 taper)`` (x east, y north), the mean of the two is the Stokes-I power beam, and a corrupted
    Stokes-I simulation through an E-field beam gives each parallel hand its own feed's response: the
    direct polarised sum's xx and yy of the same unpolarised sky."""
    from mmflow.simulate.corrupt import DayCorruptions
    from mmflow.simulate.scene import simulate_chunk, unpolarised
    from mmflow.simulate.visibilities import SkyPoints
    from mmflow.telescope.jones import JonesPowerBeam, feed_telescopes

    rng = np.random.default_rng(4)
    enu = rng.normal(size=(200, 3))
    enu[:, 2] = np.abs(enu[:, 2])
    enu /= np.linalg.norm(enu, axis=1, keepdims=True)
    jones = ShortDipoleJones(1.5)
    for feed, d in (("x", [1, 0, 0]), ("y", [0, 1, 0])):
        want = (1 - (enu @ d) ** 2) * enu[:, 2] ** 3.0
        np.testing.assert_allclose(JonesPowerBeam(jones, feed).power_enu(enu, FREQ), want, rtol=1e-12, atol=1e-15)
    feeds = [jones.power_beam(feed).power_enu(enu, FREQ) for feed in "xy"]
    np.testing.assert_allclose(0.5 * (feeds[0] + feeds[1]), jones.power_beam().power_enu(enu, FREQ), rtol=1e-12)
    with pytest.raises(Exception, match="feed"):
        JonesPowerBeam(jones, "z")

    tel = Telescope(compact_layout(5), jones.power_beam(), [FREQ], include_autos=True)
    assert [t.beam.feed for t in feed_telescopes(tel)] == ["x", "y"]
    assert feed_telescopes(Telescope(compact_layout(5), jones.power_beam("x"), [FREQ])) is None  # not Stokes I
    sky = SkyPoints(np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86]]) / np.c_[[0.9925, 1.0]], np.array([1e4, 5e3]))
    sky.vectors = sky.vectors / np.linalg.norm(sky.vectors, axis=1, keepdims=True)
    lsts = np.linspace(0.2, 0.9, 4)
    none = DayCorruptions(None, np.zeros((0, 4, 2)), np.zeros((0, 4)), [], None)
    got = simulate_chunk(tel, lsts, [sky], corrupted=[(none, [], np.zeros((0, 3)))], rows=slice(0, 4))[:, :, 0]
    want = simulate_polarised_drift_scan(tel, jones, FREQ, lsts, unpolarised(sky), correlations=("xx", "yy"))
    np.testing.assert_allclose(got, np.moveaxis(want, 1, -1), rtol=1e-5, atol=1e-2)
