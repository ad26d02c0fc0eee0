"""Antennas flagged right and wrong by the outlier search at 0-30 % noisy antennas on 42 and 256
OVRO-LWA antennas (issue 37 item 7; docs/calibration.md), over several draws of the noisy antennas.

The scene and the search are those of ``tests/unit/calibrate/test_outliers.py``. Run from the
repository root::

    python benchmarks/outlier_search.py [draws] [thermal]

(``thermal``: the thermal noise per real and imaginary part over the mean visibility amplitude, default
0.02.) Prints one JSON line per array size and fraction: noisy, flagged right, flagged wrong, summed over
the draws.
"""
import json
import sys

import numpy as np

from tests.unit.calibrate.test_outliers import noisy_search, sky_scene

draws = int(sys.argv[1]) if len(sys.argv) > 1 else 5
thermal = float(sys.argv[2]) if len(sys.argv) > 2 else 0.02
for n_ant in (42, 256):
    sky = sky_scene(n_ant, thermal)
    for fraction in (0.0, 0.1, 0.2, 0.25, 0.3):
        noisy = right = wrong = 0
        for seed in range(draws):
            bad, flagged = noisy_search(sky, fraction, seed=1000 + seed)
            hit = np.isin(flagged, bad).sum()
            noisy, right, wrong = noisy + len(bad), right + int(hit), wrong + int(len(flagged) - hit)
        print(json.dumps(dict(n_ant=n_ant, noisy_fraction=fraction, thermal=thermal, draws=draws, noisy=noisy,
                              flagged_right=right, flagged_wrong=wrong)), flush=True)
