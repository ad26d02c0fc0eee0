"""The outlier-antenna search (issue 37 item 7): exactly the noisy antennas flagged up to 30 % of the
array, on 42 and 256 antennas; 20 % of them flagged when that many are bad (the calibrate stage's
default stop can fire); an antenna flagged on a solve still pulled by the bad ones let back; noiseless
data; the search on data mmflow did not simulate; the per-bin quantiles against numpy's."""
from dataclasses import replace

import numpy as np
import pytest

from mmflow.calibrate.baselines import auto_min_lambda, baseline_lengths, baseline_mask
from mmflow.calibrate.outliers import binned_quantiles
from mmflow.calibrate.screened_gains import solve_gains_screened
from mmflow.calibrate.stefcal import dense_problem, flag_outlier_antennas, solve_gains, stefcal
from mmflow.simulate.corrupt import gain_products
from mmflow.telescope import ovro_lwa_layout
from mmflow.workflow.stages.calibrate.settings import CalibrateConfig

FREQ = 52e6
LAYOUTS = {42: dict(preset="core", radius_m=35.0), 256: dict(preset="paper-2017")}
STOP = CalibrateConfig.model_fields["max_flagged_fraction"].default  # the calibrate stage's default


def _noise_on(vis, pairs, bad, rng):
    """The cross-correlations of antennas ``bad`` replaced by complex Gaussian noise of their mean amplitude."""
    rows = (np.isin(pairs[:, 0], bad) | np.isin(pairs[:, 1], bad)) & (pairs[:, 0] != pairs[:, 1])
    if not rows.any():
        return vis
    scale = np.abs(vis[:, rows]).mean()
    vis[:, rows] = scale / np.sqrt(2) * (rng.normal(size=vis[:, rows].shape) + 1j * rng.normal(size=vis[:, rows].shape))
    return vis


@pytest.fixture(scope="module", params=sorted(LAYOUTS))
def sky(request):
    return sky_scene(request.param)


def noisy_search(sky, fraction, seed):
    """The search on ``sky`` with ``fraction`` of its antennas (drawn with ``seed``) holding noise, as
    the calibrate stage calls it: (the noisy antennas, the flagged ones)."""
    n, pairs = sky["n"], sky["pairs"]
    rng = np.random.default_rng(seed)
    bad = np.sort(rng.choice(n, int(round(fraction * n)), replace=False))
    vis = _noise_on(sky["vis"].copy(), pairs, bad, rng)
    sol = solve_gains(vis, sky["model"], 1.0, pairs, n, baseline_keep=sky["keep"], outlier_sigma=5.0,
                      baseline_lengths=sky["lengths"])
    return bad, np.flatnonzero(sol.flags[0, :, 0])


def sky_scene(n_ant, thermal=0.02):
    """Two integrations of eight point sources (a 1000 and an 800 Jy source the model holds, six of
    20-100 Jy it does not) over an OVRO-LWA layout at 52 MHz, random gains of amplitude 0.6-1.4 and any
    phase, thermal noise of ``thermal`` x the mean visibility amplitude per real and imaginary part; the
    baselines the stage keeps (``auto`` cut)."""
    layout = ovro_lwa_layout(**LAYOUTS[n_ant])
    rng = np.random.default_rng(7)
    n = layout.n_ant
    i, j = np.triu_indices(n)
    pairs = np.stack([i, j], 1)
    b = (layout.enu[j] - layout.enu[i]) * FREQ / 299792458.0
    flux = np.r_[1000.0, 800.0, rng.uniform(20, 100, 6)]
    theta, phi = rng.uniform(0, 1.2, 8), rng.uniform(0, 2 * np.pi, 8)
    vis = np.zeros((2, len(pairs), 1), complex)
    model = np.zeros_like(vis)
    for t in range(2):
        d = np.stack([np.sin(theta) * np.cos(phi + 0.01 * t), np.sin(theta) * np.sin(phi + 0.01 * t), np.cos(theta)], 1)
        fringes = flux * np.exp(-2j * np.pi * b @ d.T)  # (bl, source)
        vis[t, :, 0], model[t, :, 0] = fringes.sum(1), fringes[:, :2].sum(1)
    g = rng.uniform(0.6, 1.4, (n, 1)) * np.exp(1j * rng.uniform(-np.pi, np.pi, (n, 1)))
    vis *= gain_products(g, pairs)
    vis += thermal * np.abs(vis).mean() * (rng.normal(size=vis.shape) + 1j * rng.normal(size=vis.shape))
    keep = baseline_mask(pairs, layout.enu, FREQ, auto_min_lambda(pairs, layout.enu, FREQ))
    return dict(n=n, vis=vis, model=model, pairs=pairs, keep=keep, lengths=baseline_lengths(pairs, layout.enu, FREQ))


@pytest.mark.parametrize("fraction", [0.0, 0.1, 0.2, 0.25, 0.3])
def test_exactly_the_noisy_antennas_are_flagged(sky, fraction):
    """A fraction of the antennas hold noise instead of sky: the search (as the calibrate stage calls it,
    with the baseline lengths and its cut) flags those and no other; above 20 % of an array of more
    than 40 antennas that is more than the stage's default ``max_flagged_fraction`` (the old search,
    at most 8 one-at-a-time rounds, could not flag more than 8)."""
    bad, flagged = noisy_search(sky, fraction, seed=int(100 * fraction))
    np.testing.assert_array_equal(flagged, bad)
    assert (len(flagged) > STOP * sky["n"]) == (fraction > STOP)


def test_an_antenna_flagged_on_a_pulled_solve_is_let_back(rng, monkeypatch):
    """A solve whose gain of antenna 5 is wrong (as a first solve pulled by bad antennas can leave a good
    one): the first round flags it, and judged against the solve without it, it is let back."""
    import mmflow.calibrate.stefcal as stefcal_module

    n = 24
    i, j = np.triu_indices(n)
    pairs = np.stack([i, j], 1)
    model = rng.normal(size=(3, len(pairs), 1)) + 1j * rng.normal(size=(3, len(pairs), 1))
    g = (1 + 0.3 * rng.uniform(-1, 1, (n, 1))) * np.exp(2j * np.pi * rng.uniform(size=(n, 1)))
    vis = model * gain_products(g, pairs) + 0.01 * (rng.normal(size=model.shape) + 1j * rng.normal(size=model.shape))
    V, M, W = dense_problem(vis, model, 1.0, pairs, n, 3)
    res = stefcal(V, M, W, tol=1e-10)
    pulled = replace(res, **{k: np.copy(getattr(res, k)) for k in ("gains", "flags", "chi2", "iterations", "converged",
                                                                   "change", "antenna_change", "antenna_iterations")})
    pulled.gains[0, 5] *= np.exp(2j)  # 2 rad off: its data no longer follow the model
    rounds = []

    def judged(*args, **kw):
        rounds.append(stefcal_module_outliers(*args, **kw))
        return rounds[-1]

    stefcal_module_outliers = stefcal_module.outliers
    monkeypatch.setattr(stefcal_module, "outliers", judged)
    out, w = flag_outlier_antennas(V, M, W, pulled, n_sigma=5.0, tol=1e-10)
    assert [np.flatnonzero(r[0]).tolist() for r in rounds] == [[5], []]
    assert not out.flags.any() and (w == W).all()
    np.testing.assert_allclose(out.gains, res.gains, rtol=0, atol=1e-8)


def test_noiseless_data_flag_only_the_antenna_that_does_not_follow_the_model(rng):
    """Without noise the good antennas' residuals are round-off (their spread floored, ``MAD_FLOOR``):
    only the decorrelated antenna is flagged, and the others' gains are exact."""
    n = 16
    i, j = np.triu_indices(n)
    pairs = np.stack([i, j], 1)
    model = rng.normal(size=(2, len(pairs), 1)) + 1j * rng.normal(size=(2, len(pairs), 1))
    g = (1 + 0.3 * rng.uniform(-1, 1, n)) * np.exp(2j * np.pi * rng.uniform(size=n))
    vis = model * gain_products(g[:, None], pairs)
    sel = ((pairs[:, 0] == 4) | (pairs[:, 1] == 4)) & (pairs[:, 0] != pairs[:, 1])
    vis[:, sel] *= np.exp(1j * rng.uniform(0, 2 * np.pi, vis[:, sel].shape))
    sol = solve_gains(vis, model, 1.0, pairs, n, outlier_sigma=5.0, tol=1e-12, max_iter=2000)
    assert np.flatnonzero(sol.flags[0, :, 0]).tolist() == [4]
    ref = sol.ref_ant[0, 0]
    good = np.arange(n) != 4
    np.testing.assert_allclose(sol.gains[0, good, 0], (g * np.conj(g[ref]) / abs(g[ref]))[good], rtol=1e-10)


def test_noisy_antennas_of_data_mmflow_did_not_simulate_are_flagged():
    """A direct point-source sum (``tests/refracted_scene.py``: 40 OVRO-LWA core stands, Cyg A and Cas
    A refracted and scintillating, a 100 Jy source the model holds) with 10 antennas' baselines
    replaced by noise, solved as the calibrate stage solves (screened sources, baseline lengths): the
    10 are flagged and no other."""
    from tests.refracted_scene import FREQ as F, MIN_LAMBDA, refracted_scan

    sc = refracted_scan((330.0, 20.0, 100.0), seed=5, n_time=8)
    x, pairs = sc["x"], sc["pairs"]
    rng = np.random.default_rng(11)
    g = (1 + 0.1 * rng.normal(size=len(x))) * np.exp(1j * rng.uniform(-1, 1, len(x)))
    vis = (sc["vis"] * g[pairs[:, 0]] * np.conj(g[pairs[:, 1]]))[..., None]
    vis += 5.0 * (rng.normal(size=vis.shape) + 1j * rng.normal(size=vis.shape))
    bad = np.sort(rng.choice(len(x), 10, replace=False))
    vis = _noise_on(vis, pairs, bad, rng)
    coh = np.concatenate([sc["coh"], sc["flux"] * sc["unit"][None]])
    basis = np.concatenate([sc["basis"], np.zeros_like(sc["basis"][:1])])
    out = solve_gains_screened(vis, coh, 1.0, pairs, len(x), basis, np.array([True, True, False]),
                               baseline_keep=baseline_mask(pairs, x, F, MIN_LAMBDA),
                               baseline_lengths=baseline_lengths(pairs, x, F))
    np.testing.assert_array_equal(np.flatnonzero(out.solution.flags[0, :, 0]), bad)


def test_binned_quantiles_equal_numpys_quantile_of_each_bin(rng):
    """The typical residual per length bin, from one sort, is np.quantile of the bin (the median and the
    lower quartile; odd and even counts, empty bins NaN, ties, a NaN makes its bin NaN)."""
    for n in (0, 1, 2, 7, 40, 333):
        values = np.round(rng.random(n), 1)  # ties
        bins = rng.integers(0, 16, n)
        for q in (0.5, 0.25):
            if n > 2 and q == 0.25:
                values[0] = np.nan
            expected = [np.quantile(values[bins == b], q) if np.any(bins == b) else np.nan for b in range(16)]
            np.testing.assert_allclose(binned_quantiles(values, bins, 16, q), expected, rtol=1e-15, atol=0)
