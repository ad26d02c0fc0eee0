"""Peeling with direction-dependent gains: exact fit, gain recovery, the guard, selection."""
import numpy as np

from mmflow.calibrate.baselines import from_matrix
from mmflow.calibrate.peel import MODEL, PEEL, SKIP, SUBTRACT, peel, peel_dense, select_modes
from tests.peel_helpers import LAM, cross_weights, point_coherencies, random_array, random_directions

def test_noiseless_multi_source_peel_fits_exactly_and_recovers_dd_gains(rng):
    """Four point sources with random DD gains (+-20 % amplitude, +-0.3 pi phase per antenna).

    For point sources the model sum_s u_s u_s^H (u_s = sqrt(S_s) g_s * conj(z_s)) is invariant
    under any unitary mixing U -> U Q of the per-source antenna responses; the data fix the
    gains only up to that (a per-source phase when Q is diagonal). We assert the exact fit and
    that the recovered responses equal the truth up to a unitary Q.
    """
    N, S, n_src = 48, 3, 4
    x = random_array(rng, N)
    dirs = random_directions(rng, n_src)
    flux = np.array([1000.0, 600, 300, 150])
    M = np.broadcast_to(point_coherencies(x, dirs, flux)[:, None], (n_src, S, N, N)).copy()
    g = (1 + 0.2 * rng.uniform(-1, 1, (n_src, S, N))) * np.exp(0.3j * np.pi * rng.uniform(-1, 1, (n_src, S, N)))
    V = np.einsum("tsi,tsij,tsj->sij", g, M, np.conj(g))
    W = cross_weights(S, N)
    r = peel_dense(V, M, W, np.full((n_src, S), PEEL), passes=10, tol=1e-12, max_iter=1000)
    assert not r.guard.any() and (r.mode == PEEL).all()
    assert np.linalg.norm(r.residual * W) < 1e-6 * np.linalg.norm(V * W)
    z = np.exp(2j * np.pi * x @ dirs.T / LAM)  # (N, n_src)
    for s in range(S):
        u_true = np.sqrt(flux) * g[:, s].T * np.conj(z)
        u_est = np.sqrt(flux) * r.dd_gains[:, s].T * np.conj(z)
        q = np.linalg.lstsq(u_true, u_est, rcond=None)[0]
        assert np.linalg.norm(u_true @ q - u_est) < 1e-6 * np.linalg.norm(u_est)
        assert np.abs(q.conj().T @ q - np.eye(n_src)).max() < 1e-6


def test_peeled_source_dd_gains_recovered_up_to_a_phase_with_subtracted_neighbours(rng):
    """One peeled source, three subtracted ones with unknown flux scales: no degeneracy."""
    N, S, n_src = 48, 3, 4
    x = random_array(rng, N)
    dirs = random_directions(rng, n_src)
    flux = np.array([1000.0, 300, 200, 100])
    M = np.broadcast_to(point_coherencies(x, dirs, flux)[:, None], (n_src, S, N, N)).copy()
    g = np.ones((n_src, S, N), complex)
    g[0] = (1 + 0.3 * rng.uniform(-1, 1, (S, N))) * np.exp(0.5j * np.pi * rng.uniform(-1, 1, (S, N)))
    a = 1 + 0.5 * rng.uniform(-1, 1, (n_src, S))  # scintillating fluxes of the subtracted ones
    a[0] = 1
    V = np.einsum("tsi,tsij,tsj->sij", g * np.sqrt(a)[..., None], M, np.conj(g * np.sqrt(a)[..., None]))
    modes = np.array([PEEL, SUBTRACT, SUBTRACT, SUBTRACT])[:, None].repeat(S, 1)
    W = cross_weights(S, N)
    r = peel_dense(V, M, W, modes, passes=12, tol=1e-13, max_iter=2000)
    assert np.linalg.norm(r.residual * W) < 1e-6 * np.linalg.norm(V * W)
    ph = np.angle(np.sum(g[0] * np.conj(r.dd_gains[0]), axis=1))
    assert np.abs(r.dd_gains[0] * np.exp(1j * ph)[:, None] - g[0]).max() < 1e-6
    np.testing.assert_allclose(r.scale[1:], a[1:], rtol=1e-6)


def test_guard_turns_a_wrong_model_into_a_subtraction(rng):
    """Data: a point source. Model: the same source as a 3 deg Gaussian (resolved on most
    baselines): peeling can remove only part of it, the guard fires; the right model passes."""
    N, S = 32, 2
    x = random_array(rng, N)
    d = random_directions(rng, 1)
    point = np.broadcast_to(point_coherencies(x, d, np.array([1000.0]))[:, None], (1, S, N, N)).copy()
    wrong = np.broadcast_to(
        point_coherencies(x, d, np.array([1000.0]), [np.deg2rad(3.0)])[:, None], (1, S, N, N)
    ).copy()
    g = np.exp(0.2j * rng.normal(size=(S, N)))
    V = g[:, :, None] * point[0] * np.conj(g)[:, None, :]
    W = cross_weights(S, N)
    ok = peel_dense(V, point, W, np.full((1, S), PEEL), passes=3, tol=1e-10, max_iter=500)
    assert not ok.guard.any() and (ok.mode == PEEL).all()
    np.testing.assert_allclose(ok.removed / ok.measured, 1, atol=1e-6)
    bad = peel_dense(V, wrong, W, np.full((1, S), PEEL), passes=3, tol=1e-10, max_iter=500)
    assert bad.guard.all() and (bad.mode == SUBTRACT).all()
    assert (bad.removed / bad.measured < 0.9).all()
    # subtracted with its fitted flux instead: the residual is V minus the least-squares fit
    Mw = wrong[0] * W
    a = np.einsum("sij,sij->s", np.conj(Mw), V).real / np.einsum("sij,sij->s", np.conj(Mw), wrong[0]).real
    np.testing.assert_allclose(bad.scale[0], a, rtol=1e-10)
    np.testing.assert_allclose(bad.residual, V - a[:, None, None] * wrong[0], atol=1e-9)


def test_baseline_layout_wrapper_matches_dense_and_warm_starts(rng):
    N, T, n_src = 24, 5, 2
    x = random_array(rng, N)
    dirs = random_directions(rng, n_src)
    flux = np.array([800.0, 300])
    i, j = np.triu_indices(N)
    pairs = np.stack([i, j], 1)
    M = point_coherencies(x, dirs, flux)
    coh = np.broadcast_to(from_matrix(M, pairs)[:, None], (n_src, T, len(pairs))).copy()
    g = np.exp(0.3j * rng.normal(size=(n_src, T, N, 2))) * (1 + 0.1 * rng.normal(size=(n_src, T, N, 2)))
    vis = np.einsum("stbp,stb->tbp", g[:, :, i] * np.conj(g[:, :, j]), coh)
    modes = np.full((n_src, T), PEEL)
    w = np.ones(vis.shape)
    w[2, 7] = 0
    vis[2, 7] = np.nan  # a flagged sample may hold anything
    sol = peel(
        vis, w, coh, pairs, N, modes, dd_model="antenna", warm_start=True, batch=2, passes=8, tol=1e-12, max_iter=1000
    )
    assert sol.dd_gains.shape == (n_src, T, N, 2) and sol.residual.shape == vis.shape
    cross = (i != j) & (np.arange(len(pairs)) != 7)
    assert np.isfinite(sol.dd_gains).all()
    assert np.linalg.norm(sol.residual[:, cross]) < 1e-6 * np.linalg.norm(vis[:, cross])
    # the autocorrelations lose the sources too (subtraction acts on every baseline)
    assert np.linalg.norm(sol.residual[:, i == j]) < 1e-6 * np.linalg.norm(vis[:, i == j])


def test_single_precision_solve_agrees_with_double_to_its_tolerance(rng):
    """The stage's solve in complex64 (``dtype``; the same model copied to both polarisations, a batch
    buffer reused and a short last batch) against complex128: the same modes and guard, DD gains and
    scales within 1e-4 relative, the residual within 1e-5 of the data; ``solve_dtype`` keeps double
    precision for a tolerance single precision cannot resolve."""
    from mmflow.workflow.config.schema import load_config
    from mmflow.workflow.stages.peel.solve import solve_dtype

    N, T, n_src = 32, 7, 3
    x = random_array(rng, N)
    i, j = np.triu_indices(N)
    pairs = np.stack([i, j], 1)
    M = point_coherencies(x, random_directions(rng, n_src), np.array([5000.0, 800.0, 90.0]))
    coh = np.broadcast_to(from_matrix(M, pairs)[:, None], (n_src, T, len(pairs))).copy()
    g = np.exp(0.2j * rng.normal(size=(T, N, 2)))
    vis = (
        np.einsum("tbp,tb->tbp", g[:, i] * np.conj(g[:, j]), coh[0]) + 1.1 * coh[1][..., None] + 0.9 * coh[2][..., None]
    )
    vis = vis + 0.5 * (rng.normal(size=vis.shape) + 1j * rng.normal(size=vis.shape))
    modes = np.array([[PEEL] * T, [SUBTRACT] * T, [MODEL] * T])
    kw = dict(dd_model="antenna", batch=3, passes=3, tol=1e-4, max_iter=50)
    single = peel(vis, 1.0, coh.astype(np.complex64), pairs, N, modes, dtype=np.complex64, **kw)
    double = peel(vis, 1.0, coh, pairs, N, modes, **kw)
    assert np.array_equal(single.mode, double.mode) and np.array_equal(single.guard, double.guard)
    np.testing.assert_allclose(single.scale, double.scale, rtol=1e-4)
    np.testing.assert_allclose(single.dd_gains, double.dd_gains, rtol=0, atol=1e-4)
    assert np.abs(single.residual - double.residual).max() < 1e-5 * np.abs(vis).max()
    assert solve_dtype(load_config().peel) == np.complex64
    assert solve_dtype(load_config(overrides=["peel.tol=1e-7"]).peel) == np.complex128


def test_source_selection_by_elevation_and_apparent_flux():
    el = np.deg2rad(np.array([[-5, 5, 20, 60], [-5, 5, 20, 60], [-5, 5, 20, 60]]))
    flux = np.array([[0, 9e3, 1e4, 1.2e4], [0, 50, 300, 800], [0, 5, 20, 40]])
    modes = select_modes(flux, el, peelable=[True, True, False], peel_min_elevation_deg=[10, 45, 10],
                         subtract_min_flux_jy=1.0)
    assert modes.tolist() == [[SKIP, SUBTRACT, PEEL, PEEL], [SKIP, SUBTRACT, SUBTRACT, PEEL],
                              [SKIP, SUBTRACT, SUBTRACT, SUBTRACT]]


def test_paper_scale_256_antennas_8_sources_5_passes():
    """The benchmark's configuration without noise: refraction (3' rms at 60 MHz) and 10 %
    scintillation on 8 sources from 16 kJy to 200 Jy, from unit DD gains."""
    from mmflow.bench.calibrate import _layout

    rng = np.random.default_rng(4)
    enu, _ = _layout(256)
    N, S, n_src, lam = 256, 2, 8, 5.0
    d = rng.normal(size=(n_src, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.7
    d /= np.linalg.norm(d, axis=1)[:, None]
    flux = np.array([16000, 14000, 2500, 1800, 400, 350, 250, 200.0])
    z = np.exp(2j * np.pi * enu @ d.T / lam)
    M = np.broadcast_to((flux[:, None, None] * np.conj(z.T)[:, :, None] * z.T[:, None, :])[:, None],
                        (n_src, S, N, N)).copy()
    shift = np.deg2rad(3 / 60) * rng.normal(size=(n_src, S, 3))
    g = np.exp(-2j * np.pi * np.einsum("stk,ik->sti", shift, enu) / lam)
    g *= np.sqrt(1 + 0.1 * rng.normal(size=(n_src, S)))[..., None]
    V = np.einsum("sti,stij,stj->tij", g, M, np.conj(g))
    W = cross_weights(S, N)
    r = peel_dense(V, M, W, np.full((n_src, S), PEEL), passes=5, tol=1e-10, max_iter=300)
    assert not r.guard.any()
    assert np.linalg.norm(r.residual * W) < 1e-6 * np.linalg.norm(V * W)
    for s in range(S):  # exact up to the unitary mixing of point-source responses
        u_true = np.sqrt(flux) * g[:, s].T * np.conj(z)
        u_est = np.sqrt(flux) * r.dd_gains[:, s].T * np.conj(z)
        q = np.linalg.lstsq(u_true, u_est, rcond=None)[0]
        assert np.abs(q.conj().T @ q - np.eye(n_src)).max() < 1e-5
    # the mixing is small for the bright sources: their DD gains are recovered to ~1 %
    ph = np.angle(np.sum(g * np.conj(r.dd_gains), axis=2))
    err = np.abs(r.dd_gains * np.exp(1j * ph)[..., None] - g).max(axis=(1, 2))
    assert err[:2].max() < 0.02, err


def test_interval_dd_gains_fit_a_screen_shared_over_the_interval_with_amplitude_per_integration(rng):
    """DD gains ``sqrt(a(t)) p`` (p shared by 4 integrations, a(t) per integration, the source
    moving between integrations): with ``intervals`` the fit is exact and recovers ``p`` up to a
    phase and ``a(t)``; the per-integration fit is exact too but spends 4x the parameters, so it
    absorbs more of an unmodelled faint source (measured here: the faint source's flux removed
    along its own fringe)."""
    from mmflow.calibrate.peel import solution_intervals

    N, T = 32, 8
    x = random_array(rng, N)
    d0 = random_directions(rng, 1)[0]
    drift = np.cross(d0, [0, 0, 1.0])
    dirs = np.array([d0 + 0.02 * k * drift for k in range(T)])
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    M = np.stack([point_coherencies(x, dirs[k:k + 1], np.array([1000.0]))[0] for k in range(T)])[None]  # (1, T, N, N)
    p = (1 + 0.2 * rng.uniform(-1, 1, (2, N))) * np.exp(0.4j * np.pi * rng.uniform(-1, 1, (2, N)))
    a = 1 + 0.4 * rng.uniform(-1, 1, T)
    h = np.sqrt(a)[:, None] * p[np.arange(T) // 4]  # intervals of 4 integrations
    V = np.einsum("ti,tij,tj->tij", h, M[0], np.conj(h))
    W = cross_weights(T, N)
    intervals = solution_intervals(T, 1, 4)
    assert [i.tolist() for i in intervals] == [[[0, 1, 2, 3], [4, 5, 6, 7]]]
    r = peel_dense(V, M, W, np.full((1, T), PEEL), passes=20, tol=1e-13, max_iter=3000, intervals=intervals)
    assert np.linalg.norm(r.residual * W) < 1e-6 * np.linalg.norm(V * W)
    ratio = r.dd_gains[0] / h  # a common phase per interval, modulus 1
    for k in range(2):
        q = ratio[4 * k:4 * k + 4]
        assert np.abs(q - q[0, 0]).max() < 1e-6 and abs(abs(q[0, 0]) - 1) < 1e-6

    # an unmodelled faint source (20 Jy) elsewhere: the fitted DD gains absorb part of it
    faint = np.stack([point_coherencies(x, random_directions(np.random.default_rng(5), 1), np.array([20.0]))[0]] * T)
    fringe = faint / np.abs(faint)

    def kept(res):  # the faint source's flux along its fringe in the residual
        return np.real(np.sum(W * res * np.conj(fringe))) / np.sum(W) / 20.0

    one = peel_dense(V + faint, M, W, np.full((1, T), PEEL), passes=5, tol=1e-10, max_iter=500)
    four = peel_dense(V + faint, M, W, np.full((1, T), PEEL), passes=5, tol=1e-10, max_iter=500, intervals=intervals)
    print(
        f"faint source kept: per integration {kept(one.residual):.4f}, "
        f"4-integration intervals {kept(four.residual):.4f}"
    )
    assert 1 - kept(four.residual) < 0.5 * (1 - kept(one.residual))


def test_screen_basis_reproduces_the_simulators_refraction():
    """``sky_tangents_enu`` + ``screen_basis`` (what the peel stage fits) give the simulator's DD
    gains of a refractive offset and a flux factor (``direction_dependent_gains``) exactly."""
    from mmflow.calibrate.coherency import source_vector_date
    from mmflow.calibrate.dd_screen import screen_basis, screen_gains, sky_tangents_enu
    from mmflow.simulate.corrupt import direction_dependent_gains
    from mmflow.sky.sources import get_sources
    from mmflow.telescope import Telescope, ovro_lwa_layout
    from mmflow.telescope.beams import SinElevationBeam

    rng = np.random.default_rng(2)
    tel = Telescope(ovro_lwa_layout("core", max_antennas=30), SinElevationBeam(1.5), [50e6])
    lsts = np.deg2rad(300.0) + np.linspace(0, 0.3, 5)
    vec = np.stack([source_vector_date(s, 2457700.5) for s in get_sources(["Cyg A", "Cas A"])])
    offs = np.deg2rad(10 / 60) * rng.normal(size=(2, 5, 2))
    flux = 1 + 0.2 * rng.uniform(-1, 1, (2, 5))
    basis = screen_basis(tel.layout.enu, 50e6, sky_tangents_enu(tel, lsts, vec))
    assert basis.shape == (2, 5, tel.n_ant, 2)
    np.testing.assert_allclose(screen_gains(basis, offs, flux),
                               direction_dependent_gains(tel, 50e6, lsts, vec, offs, flux), atol=1e-12)


def test_screen_model_shared_offset_over_intervals_with_amplitude_per_integration(rng):
    """The screen model with intervals: the data's offset constant over each 4 integrations (a
    phase gradient of up to ~2 rad across the array, the source moving between integrations),
    the amplitude per integration; the fit is exact and recovers both, and the per-integration
    screen recovers them too."""
    from mmflow.calibrate.dd_screen import screen_basis, screen_gains
    from mmflow.calibrate.peel import solution_intervals

    N, T = 32, 8
    x = random_array(rng, N)
    d0 = random_directions(rng, 1)[0]
    drift = np.cross(d0, [0, 0, 1.0])
    dirs = np.array([d0 + 0.02 * k * drift for k in range(T)])
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    M = np.stack([point_coherencies(x, dirs[k:k + 1], np.array([1000.0]))[0] for k in range(T)])[None]
    east = np.cross([0, 0, 1.0], dirs)
    east /= np.linalg.norm(east, axis=1)[:, None]
    basis = screen_basis(x, 299792458.0 / LAM, np.stack([east, np.cross(dirs, east)], 1))[None]  # (1, T, N, 2)
    theta = np.deg2rad(30 / 60) * rng.normal(size=(2, 2))[np.arange(T) // 4]  # (T, 2)
    a = 1 + 0.4 * rng.uniform(-1, 1, T)
    h = screen_gains(basis[0], theta, a)
    V = np.einsum("ti,tij,tj->tij", h, M[0], np.conj(h))
    W = cross_weights(T, N)
    print(f"largest phase across the array: {np.abs(np.einsum('tak,tk->ta', basis[0], theta)).max():.2f} rad")
    for intervals in (solution_intervals(T, 1, 4), None):
        r = peel_dense(V, M, W, np.full((1, T), PEEL), passes=3, tol=1e-12, max_iter=100, intervals=intervals,
                       screen_basis=basis)
        assert np.linalg.norm(r.residual * W) < 1e-9 * np.linalg.norm(V * W)
        np.testing.assert_allclose(r.offsets[0], theta, atol=1e-10)
        np.testing.assert_allclose(np.abs(r.dd_gains[0]) ** 2, a[:, None].repeat(N, 1), rtol=1e-9)
