"""Noise weights of the m-modes: radiometer, residual-of-fit and successive-difference estimators.

A one-day drift scan at the real OVRO-LWA cadence (6628 integrations) from mmflow's
independent simulator: 40 point sources seen by four core stands (5-12 m) and two
paper-2017 stands 106 m and 160 m out, at 40 MHz, autocorrelations included.
"""
import numpy as np
import pytest

from mmflow.mmode.gapfill import lsq_mmodes
from mmflow.mmode.noise import (baseline_coverage, difference_variance, lsq_inverse_variance, lsq_mmode_variance,
                                mmode_inverse_variance, radiometer_variance, residual_variance)
from mmflow.mmode.transform import sidereal_bins

F_HZ, N_BINS, MMAX = 40e6, 6628, 200
STANDS = ["LWA-112", "LWA-113", "LWA-114", "LWA-115", "LWA-161", "LWA-293"]
DNU_TAU = 24e3 * 13.0  # OVRO-LWA channel width x integration time


@pytest.fixture(scope="module")
def scan():
    from mmflow.simulate.visibilities import SkyPoints, simulate_drift_scan
    from mmflow.telescope import Telescope, ovro_lwa_layout
    from mmflow.telescope.beams import GaussianBeam

    tel = Telescope(ovro_lwa_layout("paper-2017", stands=STANDS), GaussianBeam(30), [F_HZ])
    rng = np.random.default_rng(7)
    vec = rng.normal(size=(40, 3))
    vec /= np.linalg.norm(vec, axis=1)[:, None]
    sky = SkyPoints(vec, rng.uniform(20, 200, 40))
    pairs = tel.antenna_pairs()  # autocorrelations included
    lst = 2 * np.pi * np.arange(N_BINS) / N_BINS
    vis = simulate_drift_scan(tel, F_HZ, lst, sky, pairs)
    auto = pairs[:, 0] == pairs[:, 1]
    cross = pairs[~auto]
    mean_autos = {int(pairs[i, 0]): np.array([vis[:, i].real.mean()]) for i in np.flatnonzero(auto)}
    return {"lst": lst, "vis": vis[:, ~auto], "pairs": cross, "mean_autos": mean_autos,
            "autos": vis[:, auto].real, "band": tel.baseline_lmax(F_HZ, MMAX, cross),
            "blen": np.linalg.norm(tel.baselines_enu(cross), axis=1)}


def _weights_from(sigma2, wsum):
    return lsq_inverse_variance(sigma2, wsum)


def test_noiseless_data_weight_every_baseline_alike_with_the_radiometer_equation(scan):
    """The radiometer equation does not see the sky move: equal weights for 5 m and 160 m baselines."""
    vis, wsum = scan["vis"], np.full(scan["vis"].shape[1], float(N_BINS))
    s2 = radiometer_variance(scan["mean_autos"], scan["pairs"], DNU_TAU, 1.0)[0]
    inv = _weights_from(s2, wsum)
    assert np.all(np.isfinite(inv)) and np.all(inv > 0)
    assert inv.max() / inv.min() < 1.01
    # successive differences measure fringe motion instead: long baselines lose weight
    d = difference_variance(vis, np.ones(vis.shape))
    long, short = scan["blen"] > 100, scan["blen"] < 20
    print("noiseless difference variance short", d[short].max(), "long", d[long].min())
    assert d[long].min() > 10 * d[short].max()  # measured 15-60x


def test_injected_noise_recovered_on_short_and_long_baselines(scan):
    """Radiometer-equation noise, 5 % of integrations flagged: the fit's residual gives sigma^2 within 5 %."""
    from mmflow.simulate.visibilities import thermal_noise

    rng = np.random.default_rng(3)
    vis, pairs = scan["vis"], scan["pairs"]
    a = np.array([scan["mean_autos"][int(i)][0] for i in range(max(scan["mean_autos"]) + 1)])
    noise, sigma = thermal_noise(vis, a[pairs[:, 0]], a[pairs[:, 1]], DNU_TAU, 1.0, rng)
    true_s2 = sigma ** 2
    np.testing.assert_allclose(true_s2, radiometer_variance(scan["mean_autos"], pairs, DNU_TAU, 1.0)[0])
    flags = np.ones(vis.shape)
    flags[rng.random(N_BINS) < 0.05] = 0
    binned, wsum, offset = sidereal_bins(scan["lst"], vis + noise, flags, N_BINS, min_coverage=0.9)
    res = lsq_mmodes(binned, wsum, MMAX, scan["band"], offset)
    est = residual_variance(res.rss, res.n_filled, res.band_limit, res.signal_power)
    ratio = est / true_s2
    diff = difference_variance(vis + noise, flags) / true_s2
    print("M_b", res.band_limit, "residual / true", ratio.round(3), "differences / true", diff.round(2))
    long, short = scan["blen"] > 100, scan["blen"] < 20
    assert long.sum() >= 8 and short.sum() == 6
    assert np.all(np.abs(ratio - 1) < 0.05)  # statistical 1/sqrt(dof) ~ 1.3 %
    assert np.all(diff[long] > 3)  # the sky moves between integrations: biased high
    assert np.all(diff[long] > 3 * diff[short].max())  # and long baselines lose weight
    # the noiseless fit leaves no residual: the estimate is noise, not unmodelled sky
    clean = lsq_mmodes(*sidereal_bins(scan["lst"], vis, flags, N_BINS, 0.9)[:2], MMAX, scan["band"])
    assert np.all(clean.rss / clean.n_filled < 1e-6 * true_s2)


def test_noiseless_data_without_autocorrelations_get_finite_equal_weights(scan):
    vis = scan["vis"]
    res = lsq_mmodes(vis, np.ones(vis.shape), MMAX, scan["band"])
    s2 = residual_variance(res.rss, res.n_filled, res.band_limit, res.signal_power)
    inv = lsq_inverse_variance(s2, res.weight_sum)
    assert np.all(np.isfinite(inv)) and np.all(inv > 0)
    assert inv.max() / inv.min() < 1.01  # the floor, 1e-6 of the chunk's largest signal power
    np.testing.assert_allclose(s2, 1e-6 * res.signal_power.max())
    assert np.all(np.isinf(residual_variance(res.rss, 2 * res.band_limit + 1, res.band_limit)))  # no dof left


def test_lsq_mmode_variance_matches_monte_carlo():
    """Pure noise, 5 % random flags, 400 realisations as columns: Var(V_m) = sigma^2 / sum w."""
    rng = np.random.default_rng(4)
    n, nreal, mmax, sigma2 = 600, 400, 60, 2.5
    w = np.where(rng.random((n, 1)) < 0.05, 0.0, 1.0) * np.ones((1, nreal))
    vis = np.sqrt(sigma2 / 2) * (rng.normal(size=(n, nreal)) + 1j * rng.normal(size=(n, nreal)))
    res = lsq_mmodes(vis, w, mmax)
    emp = np.mean(np.abs(res.mmodes[:, 0]) ** 2)
    pred = lsq_mmode_variance(sigma2, res.weight_sum[0])
    assert abs(emp / pred - 1) < 0.03  # 61 x 400 samples: 0.6 % statistical
    est = residual_variance(res.rss, res.n_filled, res.band_limit)
    assert abs(np.mean(est) / sigma2 - 1) < 0.005


def test_low_coverage_never_gains_weight():
    """One baseline at 17 % coverage: today's zero-filled variance gives it 1/0.17 the weight."""
    n, nbl = 1000, 5
    w = np.ones((n, nbl))
    w[170:, 0] = 0  # 17 % coverage
    w[: n // 2, 1] = 0  # 50 %
    w[::10, 2] = 0  # 90 %
    s2 = np.ones(nbl)
    old = mmode_inverse_variance(s2, w)
    assert old[0] / np.median(old) > 5  # the defect of issue 8 item 5
    cov = baseline_coverage(w, 0.3, "downweight")
    np.testing.assert_allclose(cov.fraction, [0.17, 0.5, 0.9, 1, 1])
    new = lsq_inverse_variance(s2, w.sum(axis=0), cov)
    var = lsq_mmode_variance(s2, w.sum(axis=0))
    order = np.argsort(cov.fraction)
    assert np.all(np.diff(var[order]) <= 0) and np.all(np.diff(new[order]) >= 0)  # variance grows as coverage shrinks
    assert cov.n_downweighted == 1 and cov.n_dropped == 0
    np.testing.assert_allclose(new[0] / new[4], 0.17 * 0.17 / 0.3)
    drop = baseline_coverage(w, 0.3, "drop")
    assert drop.n_dropped == 1 and lsq_inverse_variance(s2, w.sum(axis=0), drop)[0] == 0
    # a baseline without any data (a flagged antenna, calibrated autos) is empty, not low coverage
    w[:, 3] = 0
    for policy in ("drop", "downweight"):
        c = baseline_coverage(w, 0.3, policy)
        assert c.n_empty == 1 and c.factor[3] == 0 and c.n_dropped + c.n_downweighted == 1
    from mmflow.errors import InputError

    with pytest.raises(InputError, match="coverage_policy"):
        baseline_coverage(w, 0.3, "keep")


def test_gap_weight_between_zero_and_a_real_bin():
    """sigma^2 / S: small at high signal-to-noise, capped at a filled bin's mean weight when noise dominates."""
    from mmflow.mmode.gapfill import gap_weight

    n_filled, ws = np.array([100, 100, 100, 100]), np.array([200.0, 200.0, 200.0, 200.0])
    sigma2 = np.array([1.0, 1.0, 1.0, 0.0])
    power = np.array([1 + 2 * 1e4, 1.5, 0.5, 3.0])  # sum w |V|^2 / N_filled = sigma^2 + w S
    g = gap_weight(sigma2, power, n_filled, ws)
    np.testing.assert_allclose(g[0], 1.0 * 200 / (100 * 2e4))  # sigma^2 / S with S = 1e4 per bin
    assert g[1] == 2.0 and g[2] == 2.0 and g[3] == 0.0  # at the cap (mean filled weight 2); none without noise


def test_chunk_mmodes_weights_and_coverage(scan):
    """The stage's one call: radiometer or residual noise, coverage decisions, splits."""
    from mmflow.mmode.gapfill import chunk_mmodes
    from mmflow.simulate.visibilities import thermal_noise

    rng = np.random.default_rng(9)
    vis, pairs = scan["vis"], scan["pairs"]
    a = np.array([scan["mean_autos"][int(i)][0] for i in range(max(scan["mean_autos"]) + 1)])
    noise, sigma = thermal_noise(vis, a[pairs[:, 0]], a[pairs[:, 1]], DNU_TAU, 1.0, rng)
    flags = np.ones(vis.shape)
    flags[rng.random(N_BINS) < 0.05] = 0
    flags[: int(0.8 * N_BINS), 0] = 0  # one baseline at 15 % coverage
    binned, wsum, offset = sidereal_bins(scan["lst"], vis + noise, flags, N_BINS, min_coverage=0.5)
    radio = radiometer_variance(scan["mean_autos"], pairs, DNU_TAU, 1.0)[0]
    got = chunk_mmodes(binned, wsum, MMAX, offset, scan["band"], ("full", "even", "odd"), radio, 0.5, "downweight")
    est = chunk_mmodes(binned, wsum, MMAX, offset, scan["band"], ("full",), None, 0.5, "drop")
    assert got.mmodes.shape == (3, MMAX + 1, 2, vis.shape[1])
    assert got.coverage.n_downweighted == 1 and est.coverage.n_dropped == 1 and est.inv_var[0] == 0
    ok = np.arange(vis.shape[1]) > 0
    assert np.all(np.abs(est.sigma2[ok] / sigma[ok] ** 2 - 1) < 0.05)
    np.testing.assert_allclose(est.inv_var[ok], got.inv_var[ok], rtol=0.05)
    assert got.inv_var[0] < 0.2 * np.median(got.inv_var[ok])  # low coverage: less weight, never more


def test_simulated_thermal_noise_is_real_on_autocorrelations_complex_elsewhere():
    """Radiometer noise: an autocorrelation stays real, with std V_ii / sqrt(dnu tau); a cross-
    correlation gets sqrt(V_ii V_jj / (dnu tau)) / sqrt(2) per component."""
    from mmflow.simulate.visibilities import thermal_noise

    rng = np.random.default_rng(3)
    n_t, dnu, tau = 20000, 24e3, 13.0
    pairs = np.array([(0, 0), (0, 1), (1, 1)])
    power = np.array([4e4, 0.0, 9e4])  # autos' powers; the cross row's value is unused
    vis = np.broadcast_to(power, (n_t, 3)).astype(complex)
    ai, aj = power[[0, 0, 2]], power[[0, 2, 2]]
    noise, sigma = thermal_noise(vis, ai, aj, dnu, tau, rng, pairs[:, 0] == pairs[:, 1])
    assert np.all(noise[:, [0, 2]].imag == 0)
    for c in (0, 2):
        assert np.std(noise[:, c].real) == pytest.approx(power[c] / np.sqrt(dnu * tau), rel=0.03)
    s01 = np.sqrt(power[0] * power[2] / (dnu * tau))
    assert np.std(noise[:, 1].real) == pytest.approx(s01 / np.sqrt(2), rel=0.03)
    assert np.std(noise[:, 1].imag) == pytest.approx(s01 / np.sqrt(2), rel=0.03)
