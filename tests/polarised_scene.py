"""The scene of the full-Stokes imaging tests (tests/unit/imaging/test_polarised.py and
telescope/test_jones_matvis.py): 20 antennas within 12 m at 40 MHz (baselines <= 3 wavelengths), short
dipoles with a cos^3 horizon taper, 300 integrations over a sidereal day, lmax 32."""
import numpy as np

from mmflow.analysis.peaks import measure_peak
from mmflow.conventions import radec_to_vec
from mmflow.telescope.layout import Layout

FREQ, LMAX, NSIDE, N_LST = 40e6, 32, 64, 300
NO_FILTER = dict(filter_m0=False, filter_m1_lmin=None, zero_monopole=False)
EPS_I, EPS_POL = 1e-6, 1e-4  # relative to the largest diagonal element of the Grams

# (a) polarised sources: Q/I, U/I, V/I between 5 and 50 %
POL_RADEC = np.deg2rad([[30, 60], [120, 20], [200, 45], [290, 5]])
POL_I = np.array([100.0, 80.0, 120.0, 90.0])
POL_FRAC = np.array([[0.3, 0.2, 0.05], [-0.1, 0.4, -0.1], [0.05, -0.3, 0.2], [-0.4, -0.1, 0.5]])
# (b) unpolarised sources, from 2 deg to 47 deg from the zenith at transit
UNPOL_RADEC = np.deg2rad([[40, 75], [150, -10], [260, 35], [330, 10]])
UNPOL_I = np.array([100.0, 80.0, 120.0, 90.0])


def scene_layout(n_ant=20, radius_m=12.0, seed=1):
    rng = np.random.default_rng(seed)
    pos = []
    while len(pos) < n_ant:
        p = rng.uniform(-radius_m, radius_m, 2)
        if np.hypot(*p) <= radius_m and all(np.hypot(*(p - q)) > 2.0 for q in pos):
            pos.append(p)
    enu = np.c_[np.array(pos), rng.normal(0, 0.05, n_ant)]
    return Layout([f"a{i}" for i in range(n_ant)], enu, 37.24, -118.28)


def radec_vectors(radec):
    return radec_to_vec(radec[:, 0], radec[:, 1])


def peak_near(hmap, vec, sign=1.0):
    return measure_peak(sign * hmap, vec, np.deg2rad(8))
