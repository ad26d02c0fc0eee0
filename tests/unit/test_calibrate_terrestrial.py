"""Terrestrial templates: recovered patterns, amplitude series, sky m >= 2 content kept."""
import numpy as np
import pytest

from mmflow.calibrate.baselines import baseline_mask
from mmflow.calibrate.terrestrial import (fit_amplitudes, fit_templates, projection_fraction,
                                          subtract_templates, zenith_average)
from mmflow.simulate.corrupt import crosstalk_pattern, near_field_rfi, rank1_visibilities
from mmflow.simulate.visibilities import SkyPoints, simulate_drift_scan
from mmflow.telescope import Telescope
from mmflow.telescope.beams import SinElevationBeam
from mmflow.telescope.layout import Layout

FREQ = 60e6
T = 240  # one sidereal day in 6 min steps


@pytest.fixture(scope="module")
def drift():
    rng = np.random.default_rng(7)
    n = 40
    r = 150 * np.sqrt(rng.uniform(size=n))
    a = rng.uniform(0, 2 * np.pi, n)
    enu = np.stack([r * np.sin(a), r * np.cos(a), rng.normal(0, 0.3, n)], 1)
    tel = Telescope(Layout([f"a{k}" for k in range(n)], enu, 37.24, -118.28), SinElevationBeam(1.5), [FREQ])
    vec = rng.normal(size=(30, 3))
    vec /= np.linalg.norm(vec, axis=1)[:, None]
    sky = SkyPoints(vec, rng.uniform(10, 100, 30))  # the sky after the bright sources are peeled
    lsts = 2 * np.pi * np.arange(T) / T
    pairs = tel.antenna_pairs()
    v_sky = simulate_drift_scan(tel, FREQ, lsts, sky, pairs)[..., None]
    keep = baseline_mask(pairs, enu, FREQ, 15.0)
    return tel, pairs, v_sky, keep, rng


def _corr(a, b):
    return np.abs(np.vdot(a, b)) / (np.linalg.norm(a) * np.linalg.norm(b))


@pytest.mark.parametrize("kind", ["crosstalk", "rfi"])
def test_single_template_and_amplitude_series_recovered(drift, kind):
    tel, pairs, v_sky, keep, rng = drift
    n = tel.n_ant
    if kind == "crosstalk":
        vec, amp = crosstalk_pattern(n, rng, 100.0), np.ones(T)
    else:
        vec, amp = near_field_rfi(tel.layout.enu, FREQ, T, rng, amplitude_jy=50.0)
    inj = rank1_visibilities(vec, amp, pairs)[..., None]
    vis = v_sky + inj
    mean, ws = zenith_average(vis, np.ones(vis.shape))
    tm = fit_templates(mean, ws, pairs, n, 1, baseline_keep=keep)
    b_true = rank1_visibilities(vec, np.ones(1), pairs)[0]
    assert _corr(tm.templates[0, keep, 0], b_true[keep]) > 0.99
    a = fit_amplitudes(vis, np.ones(vis.shape), tm.templates, keep)
    recon = a[:, 0, 0][:, None] * tm.templates[0, keep, 0][None]
    err = np.linalg.norm(recon - inj[:, keep, 0]) / np.linalg.norm(inj[:, keep, 0])
    # the floor: the sky's own projection on the true template (what a perfect template leaves)
    ideal = fit_amplitudes(v_sky, np.ones(vis.shape), b_true[None, :, None], keep)[:, 0, 0]
    floor = np.linalg.norm(ideal) * np.linalg.norm(b_true[keep]) / np.linalg.norm(inj[:, keep, 0])
    assert err < 1.3 * floor + 0.01, (err, floor)
    if kind == "rfi":
        scale = np.vdot(b_true[keep], tm.templates[0, keep, 0]).real / np.linalg.norm(b_true[keep]) ** 2
        assert np.corrcoef(a[:, 0, 0] * scale, amp)[0, 1] > 0.99


def test_two_components_removed_and_sky_m_ge_2_unchanged(drift):
    tel, pairs, v_sky, keep, rng = drift
    n = tel.n_ant
    c = crosstalk_pattern(n, rng, 100.0)
    e, amp = near_field_rfi(tel.layout.enu, FREQ, T, rng, amplitude_jy=50.0)
    inj = (rank1_visibilities(c, np.ones(T), pairs) + rank1_visibilities(e, amp, pairs))[..., None]
    vis = v_sky + inj
    mean, ws = zenith_average(vis, np.ones(vis.shape))
    tm = fit_templates(mean, ws, pairs, n, 2, baseline_keep=keep)
    a = fit_amplitudes(vis, np.ones(vis.shape), tm.templates, keep)
    clean = subtract_templates(vis, tm.templates, a)
    left = np.linalg.norm((clean - v_sky)[:, keep]) / np.linalg.norm(inj[:, keep])
    # limited by the sky's m = 0 part, which a stationary template cannot tell from pickup
    sky_mean = np.linalg.norm(zenith_average(v_sky, 1.0)[0][keep]) / np.linalg.norm(zenith_average(inj, 1.0)[0][keep])
    assert left < 2 * sky_mean, (left, sky_mean)
    # m-modes: V_m = (1/N) sum_n V(phi_n) exp(-i m phi_n); compare |m| >= 2
    fm = np.fft.fft(clean[:, keep, 0] - v_sky[:, keep, 0], axis=0) / T
    sm = np.fft.fft(v_sky[:, keep, 0], axis=0) / T
    im = np.fft.fft(inj[:, keep, 0], axis=0) / T
    m = np.abs(np.fft.fftfreq(T, 1 / T))
    hi = m >= 2
    change = np.linalg.norm(fm[hi]) / np.linalg.norm(sm[hi])
    # removing K real directions from each of the n_bl-dimensional v_t takes ~sqrt(K / n_bl) of
    # the sky with it (the paper's ||B^H v|| / (||B|| ||v||) ~ 0.035 is this number)
    bound = 2 * np.sqrt(2 / keep.sum())
    assert change < bound, (change, bound)
    # and the interference had real m >= 2 power (the RFI flicker) that is now gone
    assert np.linalg.norm(fm[hi]) < 0.3 * np.linalg.norm(im[hi])


def test_projection_fraction_of_a_known_response():
    rng = np.random.default_rng(0)
    B = rng.normal(size=(50, 5)) + 1j * rng.normal(size=(50, 5))
    inside = B @ (rng.normal(size=5) + 0j)
    q, _ = np.linalg.qr(B)
    outside = rng.normal(size=50) + 1j * rng.normal(size=50)
    outside -= q @ (q.conj().T @ outside)
    assert projection_fraction(B, outside) < 1e-12
    assert projection_fraction(B, inside) > 0.2
    assert projection_fraction(B, inside, ord=2) <= 1 + 1e-12
