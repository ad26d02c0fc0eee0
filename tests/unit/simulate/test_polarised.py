"""The full-Stokes simulator's sums (:func:`mmflow.simulate.polarised.simulate_polarised_drift_scan`).

An unpolarised sky is summed as Hermitian rank-k updates (``herk``) of ``sqrt(|I_s|) A_s``, sign by sign,
and a large sky in blocks of sources; both against the general product ``(A S) A^H`` of the same sky
written as the mean of two polarised skies (``Q = +-q``: by linearity their mean is the unpolarised sky's
visibilities, and they take the general path).
"""
import numpy as np

import mmflow.simulate.polarised as sim
from mmflow.telescope import Telescope
from mmflow.telescope.jones import ShortDipoleJones
from tests.polarised_scene import FREQ, radec_vectors, scene_layout


def test_unpolarised_sums_by_herk_in_blocks_equal_the_general_product(monkeypatch):
    jones = ShortDipoleJones(horizon_taper=3.0)
    tel = Telescope(scene_layout(6, 6.0), jones.power_beam(), [FREQ])
    radec = np.array([(0.3, 0.6), (1.0, 0.2), (2.0, 0.9), (2.5, 0.4), (4.0, 0.7)])
    vecs, flux = radec_vectors(radec), np.array([3.0, -1.5, 2.0, 0.7, -0.4])  # a diffuse sky's points: any sign
    lst = np.linspace(0, 2 * np.pi, 9)
    zero = np.zeros((len(flux), 3))

    def run(q, dtype=np.complex128):
        stokes = np.c_[flux, zero]
        stokes[:, 1] = q
        return sim.simulate_polarised_drift_scan(tel, jones, FREQ, lst, sim.PolarisedPoints(vecs, stokes),
                                                 dtype=dtype)

    general = 0.5 * (run(0.25) + run(-0.25))
    monkeypatch.setattr(sim, "SOURCE_BLOCK", 2)  # three blocks of sources
    herk = run(0.0)
    scale = np.abs(general).max()
    assert scale > 0.5
    np.testing.assert_allclose(herk, general, atol=1e-12 * scale)
    np.testing.assert_allclose(run(0.0, np.complex64), general, atol=2e-6 * scale)  # the diffuse samples' precision


def test_a_few_baselines_of_a_large_array_are_the_full_arrays(monkeypatch):
    """A corner turn's chunk (the baselines of two first antennas with every other one, ``few_pairs``) is
    computed between the feeds of its baselines' two ends only (one ``2|A| x 2|B|`` GEMM per integration, not
    the whole array's ``2N x 2N`` feed matrix): the full array's values for those baselines, to rounding, for a
    polarised and an unpolarised sky of sources in several blocks."""
    jones = ShortDipoleJones(horizon_taper=3.0)
    tel = Telescope(scene_layout(20, 12.0), jones.power_beam(), [FREQ])
    radec = np.array([(0.3, 0.6), (1.0, 0.2), (2.0, 0.9), (2.5, 0.4), (4.0, 0.7)])
    vecs, flux = radec_vectors(radec), np.array([3.0, -1.5, 2.0, 0.7, -0.4])
    lst = np.linspace(0, 2 * np.pi, 7)
    pairs = tel.antenna_pairs()
    chunk = pairs[(pairs[:, 0] == 2) | (pairs[:, 0] == 3)]  # i = 2, 3 and every j >= i: 37 of 210 pairs
    assert sim.few_pairs(chunk, 20) and not sim.few_pairs(pairs, 20)
    monkeypatch.setattr(sim, "SOURCE_BLOCK", 2)
    for q, u, v in ((0.0, 0.0, 0.0), (0.3, -0.2, 0.1)):
        sky = sim.PolarisedPoints(vecs, np.c_[flux, flux * q, flux * u, flux * v])
        full = sim.simulate_polarised_drift_scan(tel, jones, FREQ, lst, sky)
        part = sim.simulate_polarised_drift_scan(tel, jones, FREQ, lst, sky, pairs=chunk)
        index = [np.flatnonzero((pairs == p).all(axis=1))[0] for p in chunk]
        scale = np.abs(full).max()
        assert scale > 0.5 and part.shape == (len(lst), 4, len(chunk))
        np.testing.assert_allclose(part, full[:, :, index], atol=1e-12 * scale)
