"""Autocorrelation ripple correction: sawtooth removed, slow sky kept, gaps and edges unbiased."""
import numpy as np

from mmflow.calibrate.ripple import apply_ripple, autocorrelations, ripple_ratio
from mmflow.simulate.corrupt import antenna_gains, gain_products

DT = 13.0


def _drift(rng, n_ant=6, hours=6.0, noise=1.8e-3):
    """Autos with radiometer noise 1 / sqrt(24 kHz x 13 s); ``power`` includes that noise factor
    (the ratio r = a / s follows every sample; the test is on the smoothing, not the noise)."""
    t = np.arange(int(hours * 3600 / DT)) * DT
    g, power = antenna_gains(n_ant, 2, t, rng, bandpass=False, drift=False)
    # the sky seen by an autocorrelation: slow (sidereal-day harmonics), different per antenna/pol
    ph = rng.uniform(0, 2 * np.pi, (n_ant, 2))
    day = 86164.0
    sky = 1e4 * (1 + 0.3 * np.sin(2 * np.pi * t[:, None, None] / day + ph)
                 + 0.1 * np.sin(4 * np.pi * t[:, None, None] / day + 2 * ph))
    power = power * (1 + noise * rng.normal(size=sky.shape))
    return t, sky * power, power, sky


def test_injected_sawtooth_recovered_below_one_percent_and_sky_survives(rng):
    t, autos, power, sky = _drift(rng)
    assert np.ptp(10 * np.log10(power)) > 0.09  # the 0.1 dB sawtooth is there (2.3 % in power)
    ratio, out = ripple_ratio(autos, np.ones(autos.shape), DT)
    # a running median lags the sawtooth's drop by a sample or two: rare flags there, harmless
    assert out.mean() < 0.005
    corrected = np.where(out, np.nan, autos / ratio)
    resid = (ratio / power - 1)[~out]
    assert np.abs(resid).max() < 0.01, np.abs(resid).max()
    assert np.sqrt(np.mean(resid**2)) < 0.002
    # the slow sky variation survives: the corrected autos follow the sky, not a flat line
    assert np.nanmax(np.abs(corrected / sky - 1)) < 0.005
    assert (np.nanmax(corrected, axis=0) - np.nanmin(corrected, axis=0)).min() > 0.1 * 1e4


def test_flagged_gaps_edges_and_spikes_do_not_bias_it(rng):
    t, autos, power, sky = _drift(rng)
    w = np.ones(autos.shape)
    gap = slice(600, 740)  # a 30 min hole
    w[gap] = 0
    autos[gap] = 1e9  # flagged data may be anything
    spikes = rng.choice(len(t), 25, replace=False)
    spikes = spikes[(spikes < 600) | (spikes >= 740)]
    autos[spikes, 2, 0] *= 3.0  # unflagged RFI spikes on one antenna
    ratio, out = ripple_ratio(autos, w, DT)
    assert out[spikes, 2, 0].all()
    assert out.sum() - len(spikes) < 0.005 * out.size
    good = (w > 0) & ~out
    resid = (ratio / power - 1)[good]
    assert np.abs(resid).max() < 0.01, np.abs(resid).max()
    # edges and the samples next to the gap are as good as the middle
    edge = np.r_[0:50, len(t) - 50:len(t), 550:600, 740:790]
    assert np.abs(ratio[edge] / power[edge] - 1)[good[edge]].max() < 0.01
    assert (ratio[gap] == 1).all()


def test_applied_to_visibilities_autos_by_r_and_crosses_by_sqrt_rr(rng):
    n = 4
    i, j = np.triu_indices(n)
    pairs = np.stack([i, j], 1)
    r = 1 + 0.05 * rng.uniform(size=(3, n, 2))
    vis = rng.normal(size=(3, len(pairs), 2)) + 1j * rng.normal(size=(3, len(pairs), 2))
    vis[:, i == j] = np.abs(vis[:, i == j])
    corrupted = vis * gain_products(np.sqrt(r), pairs)
    a, w = autocorrelations(corrupted, np.ones(vis.shape), pairs, n)
    np.testing.assert_allclose(a, np.abs(vis[:, i == j]) * r)
    out, _ = apply_ripple(corrupted, np.ones(vis.shape), pairs, r)
    np.testing.assert_allclose(out, vis, atol=1e-14)
