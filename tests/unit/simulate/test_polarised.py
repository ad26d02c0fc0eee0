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
