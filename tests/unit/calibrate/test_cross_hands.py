"""The cross hands of components the parallel hands solved (:mod:`mmflow.calibrate.cross_hands`), against
the full ``2N x 2N`` feed-antenna coherency built here directly."""
import numpy as np

from mmflow.calibrate.cross_hands import (CROSS_MAX_RATIO, cross_model, fit_cross, fit_cross_bounded, gain_templates,
                                          pattern_templates)


def _pairs(n):
    return np.array([(i, j) for i in range(n) for j in range(i, n)])


def _hands(V, pairs):
    """xx, yy, xy, yx of a (..., N, 2, N, 2) coherency ``V[i, p, j, q]`` on ``pairs``: (..., bl, 4)."""
    i, j = pairs[:, 0], pairs[:, 1]
    return np.stack([V[..., i, 0, j, 0], V[..., i, 1, j, 1], V[..., i, 0, j, 1], V[..., i, 1, j, 0]], axis=-1)


def test_cross_coefficients_recover_the_feeds_phase_the_parallel_hands_cannot_see():
    """Two components ``D_s A_s A_s^H D_s^H`` (``A_s`` a random feed-antenna response, ``D_s = diag(h)`` DD gains
    per antenna and feed), summed over three integrations; the fit is given ``h`` with a different constant
    phase per feed and component (all the parallel hands fix): ``c_s = exp(-i (phi_x - phi_y))`` exactly, and
    the model is the data's xy, yx; an inactive component gets 0."""
    rng = np.random.default_rng(3)
    n, n_t = 6, 3
    pairs = _pairs(n)
    data, models, gains, want = 0, [], [], []
    for s in range(2):
        a = rng.normal(size=(n_t, n, 2)) + 1j * rng.normal(size=(n_t, n, 2))  # (time, ant, feed)
        h = np.exp(1j * rng.uniform(0, 2 * np.pi, (n_t, n, 2))) * rng.uniform(0.8, 1.2, (n_t, n, 2))
        M = a[:, :, :, None, None] * np.conj(a)[:, None, None, :, :]  # (time, i, p, j, q)
        hv = h[:, :, :, None, None] * np.conj(h)[:, None, None, :, :]
        data = data + _hands(hv * M, pairs)
        phi = rng.uniform(0, 2 * np.pi, 2)  # the per-feed phase lost in the parallel hands
        gains.append(h * np.exp(1j * phi))
        models.append(_hands(M, pairs)[..., 2:])
        want.append(np.exp(-1j * (phi[0] - phi[1])))
    T = gain_templates(np.stack(models), np.stack(gains), pairs)
    xy_yx = data[..., 2:]
    c = fit_cross(xy_yx, np.ones(xy_yx.shape), T)
    np.testing.assert_allclose(c, np.broadcast_to(want, (n_t, 2)), atol=1e-10)
    np.testing.assert_allclose(cross_model(c, T), xy_yx, atol=1e-9)
    active = np.array([[True, False, True], [True, True, True]])
    c2 = fit_cross(xy_yx, np.ones(xy_yx.shape), T, active)
    assert c2[1, 0] == 0 and abs(c2[0, 0] - want[0]) < 1e-10


def test_terrestrial_cross_block_is_in_the_span_of_the_parallel_patterns():
    """A terrestrial signal ``e e^H`` over the feeds (e.g. a polarised emitter): the parallel hands give the
    patterns ``u_p = e_p`` up to a phase per feed; its xy, yx are ``a u_x u_y^H`` and the Hermitian transpose,
    fitted exactly with weights (autocorrelations left out) and ``a = exp(i (phi_x - phi_y))``."""
    rng = np.random.default_rng(5)
    n, n_t = 5, 4
    pairs = _pairs(n)
    e = rng.normal(size=(n, 2)) + 1j * rng.normal(size=(n, 2))
    amp = rng.uniform(0.5, 2, n_t)
    V = amp[:, None, None, None, None] * e[None, :, :, None, None] * np.conj(e)[None, None, None]
    xy_yx = _hands(V, pairs)[..., 2:]
    phi = rng.uniform(0, 2 * np.pi, 2)
    u = (e * np.exp(1j * phi))[None]  # one pattern (K = 1): (K, n_ant, feed)
    w = np.ones(xy_yx.shape)
    w[:, pairs[:, 0] == pairs[:, 1]] = 0
    T = pattern_templates(u, pairs)
    a = fit_cross(xy_yx, w, T)
    np.testing.assert_allclose(a[:, 0], amp * np.exp(-1j * (phi[0] - phi[1])), rtol=1e-10)
    np.testing.assert_allclose(cross_model(a, T), xy_yx, atol=1e-9)


def test_ridge_leaves_a_component_the_cross_hands_do_not_measure():
    """A component whose cross-hand template is ~1e-9 of the data (a source where ``J_x . J_y`` vanishes) beside
    one that explains the data: without the ridge its coefficient soaks up the noise (|c| > 1e4), with it ~0, and
    the other's coefficient is the same either way."""
    rng = np.random.default_rng(7)
    n_t, n_bl = 2, 40
    strong = rng.normal(size=(n_t, n_bl, 2)) + 1j * rng.normal(size=(n_t, n_bl, 2))
    weak = 1e-9 * (rng.normal(size=(n_t, n_bl, 2)) + 1j * rng.normal(size=(n_t, n_bl, 2)))
    T = np.stack([strong, weak])
    noise = 1e-3 * (rng.normal(size=(n_t, n_bl, 2)) + 1j * rng.normal(size=(n_t, n_bl, 2)))
    data = cross_model(np.full((n_t, 2), [0.6 + 0.8j, 0.0]), T) + noise
    free = fit_cross(data, 1.0, T)
    held = fit_cross(data, 1.0, T, ridge=1e-8 * np.array([2 * n_bl, 2 * n_bl]))
    assert np.abs(free[:, 1]).max() > 1e4
    assert np.abs(held[:, 1]).max() < 1e-3  # what it subtracts: < 1e-12 of the data
    np.testing.assert_allclose(held[:, 0], 0.6 + 0.8j, atol=1e-3)


def test_bounded_fit_refuses_a_coefficient_the_data_do_not_measure():
    """A source low in the beam: its cross-hand template is 1e-4 of a bright one's and nearly the bright one's
    shape (collinear to 1e-3), with noise of 1e-3 of the data. The plain fit (the stage's 1e-8 ridge) lets it
    take a coefficient of thousands (subtracting noise along it); the bounded fit refuses it (the common
    coefficient instead, flagged) and keeps the bright source's, which the data measure, to the noise."""
    rng = np.random.default_rng(11)
    n_t, n_bl = 3, 60
    strong = rng.normal(size=(n_t, n_bl, 2)) + 1j * rng.normal(size=(n_t, n_bl, 2))
    weak = 1e-4 * (strong + 1e-3 * (rng.normal(size=strong.shape) + 1j * rng.normal(size=strong.shape)))
    T = np.stack([strong, weak])
    truth = np.array([0.6 + 0.8j, 0.7 + 0.7j])  # both ~ the XY phase
    noise = 1e-3 * (rng.normal(size=strong.shape) + 1j * rng.normal(size=strong.shape))
    data = cross_model(np.broadcast_to(truth, (n_t, 2)), T) + noise
    power = np.einsum("stbp->ts", np.abs(T) ** 2)
    free = fit_cross(data, 1.0, T, ridge=1e-8 * power)
    c, refused = fit_cross_bounded(data, 1.0, T, ridge=1e-8 * power)
    assert np.abs(free[:, 1]).max() > 100
    assert refused[:, 1].all() and not refused[:, 0].any()
    assert np.abs(c[:, 1]).max() <= CROSS_MAX_RATIO * np.abs(c[:, 0]).max()
    np.testing.assert_allclose(c[:, 0], truth[0], atol=2e-3)
    # what the bounded fit leaves in the data: the noise's level (the weak source's misfit is 1e-4 of its flux)
    assert np.abs(data - cross_model(c, T) - noise).max() < 1e-3


def test_bounded_fit_equals_the_plain_fit_where_every_coefficient_is_measured():
    """Three well-separated components of coefficients within a factor 3 of each other: nothing refused, and
    the coefficients are the plain fit's (the ridge's pull towards the common one is 1e-8 of the data's)."""
    rng = np.random.default_rng(12)
    n_t, n_bl = 2, 50
    T = rng.normal(size=(3, n_t, n_bl, 2)) + 1j * rng.normal(size=(3, n_t, n_bl, 2))
    T[2] *= 0.1
    truth = np.array([1.0, 0.8j, -1.2 + 0.3j])
    data = cross_model(np.broadcast_to(truth, (n_t, 3)), T)
    ridge = 1e-8 * np.einsum("stbp->ts", np.abs(T) ** 2)
    c, refused = fit_cross_bounded(data, 1.0, T, ridge=ridge)
    assert not refused.any()
    np.testing.assert_allclose(c, fit_cross(data, 1.0, T, ridge=ridge), atol=1e-7)
    np.testing.assert_allclose(c, np.broadcast_to(truth, (n_t, 3)), atol=1e-6)


def test_bounded_fit_from_one_normal_system_equals_refitting_the_data():
    """``fit_cross_bounded`` solves its shared coefficient and its refits from one ``G``, ``r``
    (:func:`~mmflow.calibrate.cross_hands.cross_normal`). Against the explicit route on the same data, with
    weights, inactive components and a refused one: the shared coefficient fitted to the summed active
    templates, then the refit of the data less the refused component at that coefficient (each through
    :func:`fit_cross` on the data itself)."""
    rng = np.random.default_rng(13)
    n_t, n_bl = 4, 80
    T = rng.normal(size=(4, n_t, n_bl, 2)) + 1j * rng.normal(size=(4, n_t, n_bl, 2))
    T[3] = 1e-4 * (T[0] + 1e-3 * rng.normal(size=T[0].shape))  # weak and nearly collinear: refused
    active = np.ones((4, n_t), bool)
    active[2, 1] = False
    truth = np.array([0.6 + 0.8j, 0.7 + 0.7j, -0.8 + 0.6j, 0.6 + 0.8j])
    noise = 1e-3 * (rng.normal(size=(n_t, n_bl, 2)) + 1j * rng.normal(size=(n_t, n_bl, 2)))
    data = cross_model(np.broadcast_to(truth, (n_t, 4)) * active.T, T) + noise
    w = rng.uniform(0.5, 2.0, data.shape)
    w[:, :5] = 0.0
    ridge = 1e-8 * np.einsum("stbp,tbp->ts", np.abs(T) ** 2, w)
    c, refused = fit_cross_bounded(data, w, T, active, ridge)
    assert refused[:, 3].all() and not refused[:, :3].any()

    shared = np.einsum("st,stbp->tbp", active.astype(float), T)[None]
    c_bar = fit_cross(data, w, shared)[:, 0]
    fixed = np.zeros((n_t, 4), complex)
    fixed[:, 3] = c_bar
    free = active.copy()
    free[3] = False
    want = fit_cross(data - cross_model(fixed, T), w, T, free, ridge, c_bar[:, None]) + fixed
    np.testing.assert_allclose(c, want, rtol=1e-9, atol=1e-12)
    assert (c[1, 2] == 0) and np.allclose(c[:, :2], truth[:2], atol=1e-2)
