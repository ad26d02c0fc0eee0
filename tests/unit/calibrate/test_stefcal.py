"""Stefcal: fixed point, exact recovery, autocorrelation immunity, flags, noise scaling."""
import numpy as np
import pytest

from mmflow.calibrate.baselines import baseline_mask, to_matrix
from mmflow.calibrate.gain_apply import apply_gains, apply_gains_autos
from mmflow.calibrate.outliers import MAX_EXPLAINED_RESIDUAL, antenna_statistics, outliers
from mmflow.calibrate.stefcal import dense_problem, solve_gains, stefcal, sweep
from mmflow.simulate.corrupt import gain_products


def _pairs(n):
    i, j = np.triu_indices(n)
    return np.stack([i, j], axis=1)


def _problem(rng, n_ant, n_time, n_pol=2, unity=False):
    pairs = _pairs(n_ant)
    model = rng.normal(size=(n_time, len(pairs), n_pol)) + 1j * rng.normal(size=(n_time, len(pairs), n_pol))
    auto = pairs[:, 0] == pairs[:, 1]
    model[:, auto] = np.abs(model[:, auto]) + 5
    if unity:
        g = np.ones((n_ant, n_pol), complex)
    else:
        g = (1 + 0.3 * rng.uniform(-1, 1, (n_ant, n_pol))) * np.exp(2j * np.pi * rng.uniform(size=(n_ant, n_pol)))
    vis = model * gain_products(g, pairs)
    return pairs, model, g, vis


def _square(n):
    """Index of the upper-triangle pair (i, j) (or (j, i)) of ``_pairs(n)``: (n, n)."""
    idx = np.zeros((n, n), int)
    i, j = np.triu_indices(n)
    idx[i, j] = idx[j, i] = np.arange(len(i))
    return idx


def _referenced(g, ref):
    """True gains with the phase of antenna ``ref`` removed (Stefcal's gauge)."""
    return g * np.conj(g[ref]) / np.abs(g[ref])


def test_step_at_the_optimum_is_below_n_ant_machine_epsilon(rng):
    n = 256  # the paper's array size
    pairs, model, g, vis = _problem(rng, n, 1, n_pol=1)
    V = to_matrix(vis[..., 0], pairs, n)[None]
    M = to_matrix(model[..., 0], pairs, n)[None]
    W = np.ones(V.shape)
    g0 = g[:, 0][None]
    step = sweep(V, M, W, g0) - g0
    assert np.linalg.norm(step) / np.linalg.norm(g0) < n * np.finfo(float).eps


@pytest.mark.parametrize("unity", [True, False])
@pytest.mark.parametrize("damping", ["half", "rk4"])  # undamped Stefcal oscillates
def test_gains_recovered_to_float_precision_up_to_the_phase_reference(rng, unity, damping):
    n = 24
    pairs, model, g, vis = _problem(rng, n, 3, unity=unity)
    sol = solve_gains(vis, model, np.ones(vis.shape), pairs, n, tol=1e-14, max_iter=2000, damping=damping)
    assert sol.converged.all()
    for p in range(2):
        ref = sol.ref_ant[0, p]
        err = np.abs(sol.gains[0, :, p] - _referenced(g[:, p], ref)).max()
        assert err < 1e-12, (damping, p, err)
        assert np.angle(sol.gains[0, ref, p]) == pytest.approx(0, abs=1e-15)
    assert not sol.flags.any()


def test_garbage_autocorrelations_leave_the_solution_unchanged(rng):
    n = 16
    pairs, model, g, vis = _problem(rng, n, 2)
    auto = pairs[:, 0] == pairs[:, 1]
    a = solve_gains(vis, model, np.ones(vis.shape), pairs, n, tol=1e-10)
    garbage = vis.copy()
    garbage[:, auto] = 1e9 * (rng.normal(size=garbage[:, auto].shape) + 1j)
    b = solve_gains(garbage, model, np.ones(vis.shape), pairs, n, tol=1e-10)
    np.testing.assert_array_equal(a.gains, b.gains)
    np.testing.assert_array_equal(a.chi2, b.chi2)


def test_a_flagged_antenna_gets_a_flagged_solution_and_the_rest_are_exact(rng):
    n = 16
    pairs, model, g, vis = _problem(rng, n, 2)
    w = np.ones(vis.shape)
    bad = 5
    w[:, (pairs[:, 0] == bad) | (pairs[:, 1] == bad)] = 0
    vis[:, (pairs[:, 0] == bad) | (pairs[:, 1] == bad)] = np.nan  # flagged data may be anything
    sol = solve_gains(vis, model, w, pairs, n, tol=1e-12, max_iter=500)
    assert sol.flags[0, bad].all() and (sol.gains[0, bad] == 0).all()
    assert sol.flags[0].sum() == 2  # only antenna 5, both pols
    assert (sol.ref_ant != bad).all()
    for p in range(2):
        good = np.arange(n) != bad
        assert np.abs(sol.gains[0, good, p] - _referenced(g[:, p], sol.ref_ant[0, p])[good]).max() < 1e-10
    corrected, w_out = apply_gains(vis, w, pairs, sol.gains[0], sol.flags[0])
    assert (w_out[:, (pairs[:, 0] == bad)] == 0).all()


def test_autocorrelation_powers_are_corrected_as_the_visibilities(rng):
    """The autos that set the radiometer noise are in the corrected data's units: the autos of the
    corrected data, ``|V_ii| / |g_i|^2`` (a flagged antenna's are kept: its baselines weigh 0)."""
    pairs, model, g, vis = _problem(rng, 6, 4)
    auto = pairs[:, 0] == pairs[:, 1]
    raw = np.abs(vis[:, auto])  # (time, antenna, pol): the autos of antennas 0..5 in order
    flags = np.zeros(g.shape, bool)
    flags[2, 1] = True
    out = apply_gains_autos(raw, 1e-3 * g, flags)
    corrected, _ = apply_gains(vis, np.ones(vis.shape), pairs, 1e-3 * g, flags)
    ok = ~np.broadcast_to(flags, raw.shape)
    np.testing.assert_allclose(out[ok], np.abs(corrected[:, auto])[ok], rtol=1e-12)
    np.testing.assert_allclose(out[ok], 1e6 * np.abs(model[:, auto])[ok], rtol=1e-12)
    np.testing.assert_array_equal(out[:, 2, 1], raw[:, 2, 1])


def test_a_decorrelated_antenna_is_flagged_and_no_other(rng):
    n = 20
    pairs, model, g, vis = _problem(rng, n, 2)
    vis = vis + 0.01 * (rng.normal(size=vis.shape) + 1j * rng.normal(size=vis.shape))
    sel = (pairs[:, 0] == 7) | (pairs[:, 1] == 7)
    vis[:, sel] *= np.exp(1j * rng.uniform(0, 2 * np.pi, vis[:, sel].shape))  # decorrelated antenna
    sol = solve_gains(vis, model, np.ones(vis.shape), pairs, n, outlier_sigma=5.0)
    assert sol.flags[0, 7].all()
    assert sol.flags[0].sum() == 2
    off = solve_gains(vis, model, np.ones(vis.shape), pairs, n, outlier_sigma=None)
    assert not off.flags.any()


def test_long_baseline_model_errors_flag_no_antenna_when_compared_by_length(rng):
    """One of two bright sources seen through a refractive offset: the model error ``S (e^{i k b.dtheta} - 1)``
    grows with baseline length, so the outermost antennas' plain chi2 are the array's largest
    (the paper-scale run flagged its outriggers). Compared with residuals at the same lengths
    (:func:`mmflow.calibrate.outliers.antenna_statistics`), and described by the model, no antenna is an
    outlier, while an antenna whose data do not follow the model at all is still flagged, and no other."""
    n, n_time = 40, 6
    r = np.concatenate([rng.uniform(0, 40, n - 8), rng.uniform(400, 800, 8)])  # core + outriggers (m)
    a = rng.uniform(0, 2 * np.pi, n)
    enu = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], axis=1)
    pairs = _pairs(n)
    b = enu[pairs[:, 1]] - enu[pairs[:, 0]]
    lam, offset = 4.1, np.array([2.5e-4, -1.5e-4, 0.0])  # ~1' of refraction on one of two sources
    src1, src2 = np.array([0.3, 0.2, 0.93]), np.array([-0.4, 0.5, 0.77])
    fringe = lambda d: np.exp(-2j * np.pi * (b @ d) / lam)  # noqa: E731
    model = np.repeat((1000.0 * (fringe(src1) + fringe(src2)))[None, :, None], n_time, axis=0) * np.ones((1, 1, 2))
    seen = np.repeat((1000.0 * (fringe(src1 + offset) + fringe(src2)))[None, :, None], n_time, axis=0)
    seen = seen * np.ones((1, 1, 2))
    g = (1 + 0.2 * rng.uniform(-1, 1, (n, 2))) * np.exp(2j * np.pi * rng.uniform(size=(n, 2)))
    noise = 0.5 * (rng.normal(size=seen.shape) + 1j * rng.normal(size=seen.shape))
    vis = seen * gain_products(g, pairs) + noise
    lengths = np.linalg.norm(b, axis=1)
    w = np.ones(vis.shape)
    # by the rank of their residuals the outriggers stand out against the whole array (most of their 16
    # antenna-pols), hardly against baselines of their lengths, and the model leaves little of their
    # signal unexplained, which keeps them all
    sol = solve_gains(vis, model, w, pairs, n, outlier_sigma=None)
    V, M, W = dense_problem(vis, model, w, pairs, n, n_time)
    partners = ~sol.flags[0].T
    x, unexplained = antenna_statistics(V, M, W, sol.gains[0].T, partners)
    assert outliers(x, partners)[:, n - 8:].sum() >= 8 and not outliers(x, partners)[:, :n - 8].any()
    x, unexplained = antenna_statistics(V, M, W, sol.gains[0].T, partners, np.linalg.norm(b, axis=1)[_square(n)])
    assert outliers(x, partners).sum() <= 2
    assert (unexplained < MAX_EXPLAINED_RESIDUAL).all() and not outliers(x, partners, unexplained).any()
    by_length = solve_gains(vis, model, w, pairs, n, outlier_sigma=5.0, baseline_lengths=lengths)
    assert not by_length.flags.any()
    bad = vis.copy()
    sel = (pairs[:, 0] == 3) | (pairs[:, 1] == 3)
    bad[:, sel] *= np.exp(1j * rng.uniform(0, 2 * np.pi, bad[:, sel].shape))  # a core antenna decorrelated
    sol = solve_gains(bad, model, w, pairs, n, outlier_sigma=5.0, baseline_lengths=lengths)
    assert sol.flags[0, 3].all() and sol.flags[0].sum() == 2, np.argwhere(sol.flags[0])


def test_gain_error_scales_as_sigma_over_flux_sqrt_nant_nint(rng):
    """Point source of flux S on every baseline, unit gains; independent trials as solutions."""
    S, sigma, trials = 10.0, 2.0, 300
    ratios = []
    for n, k in [(8, 1), (32, 1), (8, 8)]:
        M = np.full((trials, k, n, n), S, complex)
        noise = sigma / np.sqrt(2) * (rng.normal(size=M.shape) + 1j * rng.normal(size=M.shape))
        noise = np.triu(noise, 1)
        noise = noise + np.conj(np.swapaxes(noise, -1, -2))
        res = stefcal(M + noise, M, np.ones(M.shape), tol=1e-10, max_iter=500)
        rms = np.sqrt(np.mean((np.abs(res.gains) - 1) ** 2))  # amplitude: free of the phase gauge
        ratios.append(rms * S * np.sqrt(n * k) / sigma)
    ratios = np.array(ratios)
    # sigma_|g| = sigma / (S sqrt(2 (N - 1) K)): ~0.76 and ~0.72 for N = 8, 32
    assert np.all((ratios > 0.6) & (ratios < 0.85)), ratios
    assert ratios.max() / ratios.min() < 1.15, ratios


def test_baseline_mask_excludes_short_baselines_and_autos():
    enu = np.array([[0, 0, 0], [10, 0, 0], [200, 0, 0.0]])
    pairs = _pairs(3)
    keep = baseline_mask(pairs, enu, 74e6, min_lambda=15.0)
    # 10 m = 2.5 lambda (dropped), 200 m = 49 lambda, 190 m = 47 lambda (kept), autos dropped
    assert keep.tolist() == [False, False, True, False, True, False]


def test_solution_intervals_follow_time_varying_gains(rng):
    n, T = 12, 6
    pairs, model, _, _ = _problem(rng, n, T, n_pol=1)
    g = np.exp(1j * rng.uniform(0, 2 * np.pi, (T, n, 1))) * (1 + 0.1 * rng.normal(size=(T, n, 1)))
    g[1::2] = g[0::2]  # constant within intervals of 2
    vis = model * gain_products(g, pairs)
    sol = solve_gains(vis, model, np.ones(vis.shape), pairs, n, solint=2, tol=1e-13, max_iter=1000)
    assert sol.gains.shape == (3, n, 1)
    corrected, _ = apply_gains(vis, np.ones(vis.shape), pairs, sol.gains[np.arange(T) // 2])
    np.testing.assert_allclose(corrected, model, rtol=0, atol=1e-10 * np.abs(model).max())


def test_a_solution_spans_channels_and_integrations(rng):
    """(time, chan, bl, pol) data: one gain per antenna and pol fits every channel and time."""
    n, T, C = 10, 3, 4
    pairs = _pairs(n)
    model = rng.normal(size=(T, C, len(pairs), 2)) + 1j * rng.normal(size=(T, C, len(pairs), 2))
    g = np.exp(2j * np.pi * rng.uniform(size=(n, 2))) * (1 + 0.2 * rng.uniform(-1, 1, (n, 2)))
    vis = model * gain_products(g, pairs)
    sol = solve_gains(vis, model, np.ones(vis.shape), pairs, n, tol=1e-13, max_iter=1000)
    assert sol.gains.shape == (1, n, 2)
    for p in range(2):
        assert np.abs(sol.gains[0, :, p] - _referenced(g[:, p], sol.ref_ant[0, p])).max() < 1e-10
    # zero weight on all but one channel gives the same answer from that channel alone
    w = np.zeros(vis.shape)
    w[:, 2] = 1
    one = solve_gains(vis, model, w, pairs, n, tol=1e-13, max_iter=1000)
    np.testing.assert_allclose(one.gains, sol.gains, atol=1e-10)


def test_compiled_sweep_equals_the_plain_numpy_update(rng):
    """Upper-triangle numba sweep vs the full-matrix numpy formula, with weights and flags."""
    from mmflow.calibrate.stefcal import sweep_numpy

    n, S, K = 40, 3, 2
    pairs = _pairs(n)
    shape = (S, K, len(pairs))
    V = to_matrix(rng.normal(size=shape) + 1j * rng.normal(size=shape), pairs, n)
    M = to_matrix(rng.normal(size=shape) + 1j * rng.normal(size=shape), pairs, n)
    W = to_matrix(rng.uniform(0.5, 2, shape) * (rng.uniform(size=shape) > 0.2), pairs, n)
    W[:, :, 3, :] = W[:, :, :, 3] = 0  # a flagged antenna
    g = np.exp(1j * rng.uniform(0, 6, (S, n))) * rng.uniform(0.5, 1.5, (S, n))
    for threads in (1, 3):
        ours = sweep(V, M, W, g, threads=threads)
        ref = sweep_numpy(V, M, W, g)
        np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-12)
        assert (ours[:, 3] == 0).all()


def test_calibration_track_is_where_both_calibrators_are_high():
    from mmflow.calibrate.stefcal import best_track

    t = np.arange(200)
    cyg = np.exp(-0.5 * ((t - 80) / 30) ** 2)
    cas = np.exp(-0.5 * ((t - 120) / 30) ** 2)
    tr = best_track(np.stack([cyg, cas]), 20)
    assert tr == slice(90, 110)  # centred between the two transits
    w = np.ones(200)
    w[95] = 0
    tr = best_track(np.stack([cyg, cas]), 20, w)
    assert not (tr.start <= 95 < tr.stop)


def test_apply_gains_equals_the_division_in_place_and_broadcasts_one_integration():
    """``apply_gains`` (reciprocal gains, one compiled pass) equals ``V / (g_i conj(g_j))`` with
    flagged antennas and gains of 0 zeroed, for float32 data to the last bit and complex128 data to
    rounding, also for the cross hands (feed p of i, q of j) and in place; gains of one integration
    apply to every integration; gains for another number of integrations are refused."""
    rng = np.random.default_rng(3)
    n, T = 9, 37
    i, j = np.triu_indices(n)
    pairs = np.stack([i, j], 1)
    vis = (rng.normal(size=(T, len(pairs), 2)) + 1j * rng.normal(size=(T, len(pairs), 2))).astype(np.complex64)
    g = rng.normal(size=(T, n, 2)) + 1j * rng.normal(size=(T, n, 2))
    g[:, 2] = 0
    flags = np.zeros(g.shape, bool)
    flags[5:9, 4] = True
    w = rng.uniform(0.5, 1, size=vis.shape).astype(np.float32)
    out, wout = apply_gains(vis, w, pairs, g, flags)
    prod = g[:, i] * np.conj(g[:, j])
    bad = (prod == 0) | flags[:, i] | flags[:, j]
    ref = np.where(bad, 0, vis / np.where(bad, 1, prod)).astype(np.complex64)
    assert out.dtype == np.complex64 and np.array_equal(out, ref)
    assert np.array_equal(wout, np.where(bad, 0.0, w)) and bad.any() and not bad.all()
    # the cross hands in double precision, in place
    v2, w2 = vis.astype(np.complex128), w.astype(float)
    feeds = ((0, 1), (1, 0))
    prod = g[:, i][..., [0, 1]] * np.conj(g[:, j][..., [1, 0]])
    bad = (prod == 0) | flags[:, i][..., [0, 1]] | flags[:, j][..., [1, 0]]
    ref = np.where(bad, 0, v2 / np.where(bad, 1, prod))
    got = apply_gains(v2, w2, pairs, g, flags, feeds=feeds, out=(v2, w2))
    assert got[0] is v2 and got[1] is w2
    np.testing.assert_allclose(v2, ref, rtol=1e-14, atol=0)
    assert np.array_equal(v2 == 0, bad) and np.array_equal(w2, np.where(bad, 0.0, w))
    one, _ = apply_gains(vis, 1.0, pairs, g[:1], flags[:1])
    same, _ = apply_gains(vis, 1.0, pairs, g[0], flags[0])
    assert np.array_equal(one, same)
    with pytest.raises(ValueError, match="gains for 3 integrations, data for 37"):
        apply_gains(vis, 1.0, pairs, g[:3])


def test_to_matrix_equals_a_loop_over_baselines(rng):
    """The compiled scatter against a plain loop: conj(V_ij) at [j, i] first, then V_ij at [i, j] (an
    autocorrelation keeps V_ii; a pair listed both ways keeps the [i, j] writes), ``fill`` elsewhere,
    complex and real input, an ``out`` of wider dtype, a non-contiguous input."""
    pairs = np.array([[0, 1], [1, 0], [2, 2], [3, 1], [4, 0]])
    vis = rng.normal(size=(3, 2, 5)) + 1j * rng.normal(size=(3, 2, 5))
    for x, fill, out in ((vis, 0.0, None), (vis.real, -1.0, None), (vis[..., ::-1], 2.5, None),
                         (vis.astype(np.complex64), 0.0, np.empty((3, 2, 6, 6), np.complex128))):
        ref = np.full(x.shape[:-1] + (6, 6), fill, x.dtype if out is None else out.dtype)
        for k, (i, j) in enumerate(pairs):
            ref[..., j, i] = np.conj(x[..., k])
        for k, (i, j) in enumerate(pairs):
            ref[..., i, j] = x[..., k]
        got = to_matrix(x, pairs, 6, fill=fill, out=out)
        assert got.dtype == ref.dtype and np.array_equal(got, ref)
    with pytest.raises(ValueError, match="complex visibilities"):
        to_matrix(vis, pairs, 6, out=np.empty((3, 2, 6, 6)))
    for short in (vis[..., :4], vis[..., :1], np.ones((1, 2000))):  # never past the pairs' end
        with pytest.raises(ValueError, match="the 5 baselines of pairs"):
            to_matrix(short, pairs, 6)
