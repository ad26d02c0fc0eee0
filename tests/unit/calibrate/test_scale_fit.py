"""Joint scales in peeling, modelled (kept) sources, and interpolated gain tables."""
import numpy as np

from mmflow.calibrate.gain_tables import gains_at
from mmflow.calibrate.peel import MODEL, PEEL, SKIP, SUBTRACT, add_component, peel_dense, select_modes
from mmflow.calibrate.scale_fit import fit_scales
from tests.peel_helpers import cross_weights, point_coherencies, random_array, random_directions


def _least_squares_scales(R, comps, W):
    """Independent: the real least-squares scales of ``R ~ sum_s a_s C_s`` over the weighted cross
    baselines, one solution at a time, by numpy's lstsq on the stacked real and imaginary parts."""
    out = []
    for k in range(R.shape[0]):
        w = np.sqrt(W[k]).ravel()
        A = np.stack([c[k].ravel() * w for c in comps], 1)
        y = R[k].ravel() * w
        out.append(np.linalg.lstsq(np.concatenate([A.real, A.imag]), np.concatenate([y.real, y.imag]),
                                   rcond=None)[0])
    return np.array(out).T


def test_joint_scales_equal_least_squares_for_overlapping_fringes_and_skip_a_null_model(rng):
    """Two sources 2 deg apart on a 200 m array (strongly correlated fringes) and one whose model is
    0 (at the horizon), random baseline weights, 1e5 Jy in the autocorrelations (never fitted) and
    one solution where nothing is selected (flagged): the joint fit equals an independent weighted
    least squares over the cross baselines for the two, to 1e-9, leaves the null one and the
    unselected solution at their old scales, and leaves in the residual what the scales leave."""
    N, S = 20, 4
    x = random_array(rng, N)
    d0 = random_directions(rng, 1)[0]
    d1 = d0 + np.deg2rad(2.0) * np.cross(d0, [0, 0, 1]) / np.linalg.norm(np.cross(d0, [0, 0, 1]))
    dirs = np.array([d0, d1 / np.linalg.norm(d1), d0])
    M = point_coherencies(x, dirs, np.array([500.0, 300.0, 1.0]))
    M[2] = 0.0  # a model that is exactly zero
    coh = np.broadcast_to(M[:, None], (3, S, N, N)).copy()
    truth = np.array([[0.9, 1.1, 1.0], [1.2, 0.7, 1.0], [0.5, 1.5, 1.0], [1.0, 1.0, 1.0]]).T  # (src, S)
    noise = 0.5 * (rng.normal(size=(S, N, N)) + 1j * rng.normal(size=(S, N, N)))
    V = np.einsum("ks,ksij->sij", truth, coh) + noise + np.conj(np.swapaxes(noise, 1, 2))
    V[:, np.arange(N), np.arange(N)] += 1e5  # receiver power in the autocorrelations
    W = rng.uniform(0.2, 3.0, (S, N, N))
    W = W + np.swapaxes(W, 1, 2)  # symmetric, autos weighted too: fit_scales must skip them
    sel = np.ones((3, S), bool)
    sel[:, 3] = False  # a flagged solution
    R = V.copy()
    scale = np.ones((3, S))
    scale[2] = 0.25
    scale[:, 3] = 0.6
    for s in range(3):
        add_component(R, coh[s], np.ones((S, N), complex), -scale[s] * sel[s])
    fit_scales(R, coh, W, scale, sel)
    W_cross = W * ~np.eye(N, dtype=bool)
    expect = _least_squares_scales(V[:3], [coh[0][:3], coh[1][:3]], W_cross[:3])
    np.testing.assert_allclose(scale[:2, :3], expect, rtol=0, atol=1e-9)
    assert np.all(scale[2, :3] == 0.25) and np.all(scale[:, 3] == 0.6)
    np.testing.assert_allclose(R[:3], V[:3] - np.einsum("ks,ksij->sij", scale[:2, :3], coh[:2, :3]), atol=1e-8)
    np.testing.assert_array_equal(R[3], V[3])


def test_joint_scales_of_sources_apart_in_the_stack_ignore_the_unselected_between(rng):
    """Sources 0 and 3 selected, 1 (bright, 20x) and 2 between them selected nowhere: the fit (which
    takes the stack's rows 0..3 as one view) equals the independent least squares of 0 and 3 alone
    against the data (1 and 2 in it),
    leaves 1 and 2's scales and their flux in the residual, and equals the fit on a stack that is not
    contiguous (the copied rows)."""
    N, S = 16, 3
    x = random_array(rng, N)
    M = point_coherencies(x, random_directions(rng, 4), np.array([300.0, 6000.0, 50.0, 200.0]))
    coh = np.broadcast_to(M[:, None], (4, S, N, N)).copy()
    noise = 0.5 * (rng.normal(size=(S, N, N)) + 1j * rng.normal(size=(S, N, N)))
    V = 0.8 * coh[0] + coh[1] + coh[2] + 1.3 * coh[3] + noise + np.conj(np.swapaxes(noise, 1, 2))
    W = cross_weights(S, N).astype(float)
    sel = np.zeros((4, S), bool)
    sel[[0, 3]] = True
    results = []
    for stack in (coh, np.asfortranarray(coh)):
        R = V.copy()
        scale = np.array([[1.0] * S, [0.5] * S, [0.25] * S, [1.0] * S])
        for s in (0, 3):
            add_component(R, coh[s], np.ones((S, N), complex), -scale[s])
        fit_scales(R, stack, W, scale, sel)
        results.append((scale, R))
        expect = _least_squares_scales(V, [coh[0], coh[3]], W)  # 1 and 2 stay in the data
        np.testing.assert_allclose(scale[[0, 3]], expect, rtol=0, atol=1e-9)
        assert np.all(scale[1] == 0.5) and np.all(scale[2] == 0.25)
        np.testing.assert_allclose(R, V - scale[0][:, None, None] * coh[0] - scale[3][:, None, None] * coh[3],
                                   atol=1e-8)
    np.testing.assert_allclose(results[0][0], results[1][0], rtol=1e-12)


def test_guard_refits_the_other_scales_once_a_peel_is_undone():
    """A peeled source absent from the data in two solutions (a wrong model): the guard turns it
    into a subtraction there, and the subtracted and modelled sources' scales, first fitted beside
    DD gains that absorbed part of them, are refitted: the subtracted source's scale is its true
    1.05 to the noise in every solution, and the residual is the modelled sources plus noise.
    (Before the refit the subtracted scale stayed at its start, 1.000, where the guard fired: 20 Jy
    rms of residual against 2 Jy of noise.)"""
    rng = np.random.default_rng(5)  # a draw where the DD gains absorb enough for the guard to fire
    N, S = 24, 4
    x = random_array(rng, N)
    M = point_coherencies(x, random_directions(rng, 4), np.array([2000.0, 400.0, 60.0, 30.0]))
    coh = np.broadcast_to(M[:, None], (4, S, N, N)).copy()
    present = np.array([0.0, 0.0, 1.0, 1.0])
    noise = 2 * (rng.normal(size=(S, N, N)) + 1j * rng.normal(size=(S, N, N)))
    noise = (noise + np.conj(np.swapaxes(noise, 1, 2))) / 2
    V = present[:, None, None] * coh[0] + 1.05 * coh[1] + 0.93 * coh[2] + 1.1 * coh[3] + noise
    modes = np.array([[PEEL] * S, [SUBTRACT] * S, [MODEL] * S, [MODEL] * S])
    r = peel_dense(V, coh, cross_weights(S, N), modes, passes=4, tol=1e-10, max_iter=300)
    assert r.guard[0, :2].all() and not r.guard[0, 2:].any()
    np.testing.assert_allclose(r.scale[1], 1.05, atol=0.005)
    off = ~np.eye(N, dtype=bool)
    left = (r.residual - 0.93 * coh[2] - 1.1 * coh[3] - noise)[:2][:, off]
    assert np.sqrt(np.mean(np.abs(left) ** 2)) < 0.5 * np.sqrt(np.mean(np.abs(noise[:2][:, off]) ** 2))


def test_modelled_source_is_fitted_with_the_others_and_left_in_the_data(rng):
    """Noiseless: a peeled source with DD gains, a subtracted one and a modelled one of scale 0.93.
    The residual is exactly the modelled source's visibilities; its fitted scale is 0.93; the
    modelled source is never peeled even when it is peelable."""
    N, S = 24, 4
    x = random_array(rng, N)
    dirs = random_directions(rng, 3)
    M = point_coherencies(x, dirs, np.array([2000.0, 400.0, 60.0]))
    coh = np.broadcast_to(M[:, None], (3, S, N, N)).copy()
    g = np.exp(0.3j * rng.normal(size=(S, N))) * (1 + 0.1 * rng.normal(size=(S, N)))
    V = g[:, :, None] * np.conj(g)[:, None, :] * coh[0] + 1.05 * coh[1] + 0.93 * coh[2]
    modes = np.array([[PEEL] * S, [SUBTRACT] * S, [MODEL] * S])
    r = peel_dense(V, coh, cross_weights(S, N), modes, passes=8, tol=1e-12, max_iter=1000)
    np.testing.assert_allclose(r.scale[1], 1.05, atol=1e-6)
    np.testing.assert_allclose(r.scale[2], 0.93, atol=1e-6)
    assert (r.mode == modes).all()
    off = ~np.eye(N, dtype=bool)
    assert np.abs(r.residual - 0.93 * coh[2])[:, off].max() < 1e-6 * np.abs(V).max()
    el = np.deg2rad(np.array([[-5.0, 30.0], [-5.0, 30.0]]))
    sel = select_modes(np.full((2, 2), 100.0), el, peelable=[True, True], modelled=[False, True])
    assert sel.tolist() == [[SKIP, PEEL], [SKIP, MODEL]]


def test_cold_start_fits_scintillating_sources_exactly(rng):
    """The peeled source's flux jumps by up to 50 % from one integration to the next (scintillation),
    next to a subtracted and a modelled source: each integration, started from unit gains (the
    stage's default, ``peel.warm_start: false``), is fitted to 1e-6 of the data (converged)."""
    N, S = 24, 6
    x = random_array(rng, N)
    dirs = random_directions(rng, 3)
    M = point_coherencies(x, dirs, np.array([5000.0, 800.0, 100.0]))
    coh = np.broadcast_to(M[:, None], (3, S, N, N)).copy()
    f = np.array([1.0, 1.5, 0.7, 1.3, 0.8, 1.1])
    V = f[:, None, None] * coh[0] + coh[1] + coh[2]
    modes = np.array([[PEEL] * S, [SUBTRACT] * S, [MODEL] * S])
    r = peel_dense(V, coh, cross_weights(S, N), modes, passes=8, tol=1e-12, max_iter=1000)
    off = ~np.eye(N, dtype=bool)
    assert np.abs(r.residual - coh[2])[:, off].max() < 1e-6 * np.abs(V).max()
    np.testing.assert_allclose(np.mean(np.abs(r.dd_gains[0]) ** 2, axis=1), f, rtol=1e-6)


def test_interpolated_gains_follow_a_linear_drift_and_respect_flags():
    """Solutions at the centres of 10-integration intervals of gains whose amplitudes and phases
    drift linearly at a different rate per antenna (one phase crossing +-pi), each interval with
    its own arbitrary phase reference (Stefcal's reference antenna may change): interpolation
    reproduces every product ``g_i conj(g_j)`` exactly between the first and last centres and holds
    the end solutions outside; without it each interval's solution is held; a flagged solution
    flags the integrations that use it."""
    rows = np.arange(40)
    intervals = np.array([[0, 10], [10, 20], [20, 30], [30, 40]])
    centre = intervals.mean(1) - 0.5
    rate = np.array([0.02, -0.015, 0.035])[:, None]  # rad per integration, per antenna
    slope = np.array([0.01, -0.004, 0.0])[:, None]

    def true(t):  # (time, antenna, pol)
        t = np.asarray(t, float)[:, None, None]
        return (1.0 + slope * t) * np.exp(1j * (np.array([2.9, -1.0, 0.4])[:, None] + rate * t)) * np.ones((1, 3, 2))

    def products(g):
        i, j = np.triu_indices(3, 1)
        return g[:, i] * np.conj(g[:, j])

    reference = np.exp(1j * np.array([0.0, 3.0, -0.2, 2.9]))[:, None, None]  # per interval: steps near pi
    sol = true(centre) * reference
    flags = np.zeros(sol.shape, bool)
    g, fl = gains_at(rows, sol, flags, intervals, interpolate=True)
    inside = (rows >= centre[0]) & (rows <= centre[-1])
    np.testing.assert_allclose(products(g[inside]), products(true(rows[inside])), atol=1e-12)
    before = rows < centre[0]
    np.testing.assert_allclose(products(g[before]), products(sol[[0] * before.sum()]), atol=1e-12)
    g0, _ = gains_at(rows, sol, flags, intervals, interpolate=False)
    np.testing.assert_array_equal(g0, sol[rows // 10])
    flags[2, 1, 0] = True
    g, fl = gains_at(rows, sol, flags, intervals, interpolate=True)
    uses_2 = (rows > centre[1]) & (rows < centre[3])
    assert fl[uses_2, 1, 0].all() and not fl[~uses_2, 1, 0].any() and not fl[:, 0].any()
    assert (g[fl] == 0).all()
    g, fl = gains_at(np.array([45]), sol, np.zeros(sol.shape, bool), intervals, interpolate=True)
    assert fl.all() and (g == 0).all()  # outside every interval


def test_modelled_sources_are_refused_when_also_removed_or_unknown():
    """A source is either removed (``peel.sources``) or modelled and kept, never both; names are
    checked against the catalogue, before any work."""
    from tests.workflow_helpers import refused_problem

    cal = "workflows/demo-calibrate.yaml"
    (_, _, problem, fix), _ = refused_problem(["peel.model_sources=[Tau A, 3C 48]"], "peel.model_sources", cal)
    assert "Tau A" in str(problem) or "peel.sources" in problem
    assert "one of the two lists" in fix
    (_, _, problem, fix), _ = refused_problem(["peel.model_sources=[3C 4B]"], "peel.model_sources", cal)
    assert "catalogue" in problem and "3C 48" in fix


def test_duplicate_and_misspelt_source_names_are_refused():
    from tests.workflow_helpers import refused_problem

    cal = "workflows/demo-calibrate.yaml"
    (_, _, problem, fix), _ = refused_problem(["peel.model_sources=[3C 48, 3C 48]"], "peel.model_sources", cal)
    assert "more than once" in problem
    (_, _, problem, fix), _ = refused_problem(["models.enabled=true", "models.components={Cyg  A: 4}"],
                                              "models.components", cal)
    assert "catalogue" in problem and "Cyg A" in fix
