"""A band-limited sky's drift scan from 2 L + 1 + margin sidereal angles (mmflow.simulate.drift_modes)."""
import numpy as np

from mmflow.simulate import drift_modes as dm
from mmflow.simulate.scene import diffuse_points
from mmflow.simulate.visibilities import simulate_drift_scan


def test_a_trigonometric_polynomial_of_degree_l_is_recovered_exactly(rng):
    """Known answer: V(phi) = sum_{|m| <= L} v_m e^{i m phi} with random v_m, sampled at sample_lsts(L),
    evaluates to itself at arbitrary angles to rounding; a mode above L would be dropped."""
    L = 11
    m = np.arange(-L, L + 1)
    v = rng.normal(size=(len(m), 3)) + 1j * rng.normal(size=(len(m), 3))

    def V(phi):
        return np.exp(1j * np.outer(phi, m)) @ v

    phi = rng.uniform(-7, 7, 50)
    got = dm.evaluate_drift(dm.coefficients_from_samples(V(dm.sample_lsts(L))), phi, L)
    np.testing.assert_allclose(got, V(phi), rtol=0, atol=1e-12 * np.abs(v).sum())
    assert dm.n_samples(L) >= 2 * L + 1 and dm.n_samples(L) % 2 == 0


def test_the_diffuse_skys_drift_scan_interpolates_the_direct_sum(small_telescope):
    """The synthetic diffuse sky (band limit 12) through the simulator at 2 L + 10 angles, interpolated,
    equals the direct sum at other angles to 1e-6 of the largest visibility (the quadrature's own
    residue; the thermal noise of a 13 s, 24 kHz visibility is ~3e-3 of it)."""
    tel, f, L = small_telescope, 40e6, 12
    pts = diffuse_points(tel, f, 2457802.0, L, seed=3, quad_oversample=16)
    pairs = tel.antenna_pairs()
    lsts = np.array([0.1, 1.7, 3.3, 5.9])
    direct = simulate_drift_scan(tel, f, lsts, pts, pairs)
    coeffs = dm.coefficients_from_samples(simulate_drift_scan(tel, f, dm.sample_lsts(L), pts, pairs))
    got = dm.evaluate_drift(coeffs, lsts, L)
    assert np.abs(got - direct).max() < 1e-6 * np.abs(direct).max()
    # the modes above L hold only that residue
    m = np.rint(np.fft.fftfreq(len(coeffs), 1 / len(coeffs))).astype(int)
    assert np.abs(coeffs[np.abs(m) > L]).max() < 1e-6 * np.abs(coeffs).max()
