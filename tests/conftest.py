import os

import numpy as np
import pytest

os.environ.setdefault("MMFLOW_THREADS", "2")


def pytest_collection_modifyitems(config, items):
    """Tests in three tiers: ``tests/unit`` (kernels on in-memory arrays, ``make test-fast``),
    ``tests/workflow`` (stages and runs at small scale) and ``tests/acceptance`` (the README tour, the
    demos, faults, clusters, real files and matvis scans at scale), marked ``slow``
    (``pytest -m "not slow"`` leaves them out)."""
    for item in items:
        if "acceptance" in item.path.parts:
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session")
def small_telescope():
    """Eight real OVRO-LWA core stands within 15 m, a beam smooth at the horizon, 40 MHz."""
    from mmflow.telescope import Telescope, ovro_lwa_layout
    from mmflow.telescope.beams import GaussianBeam

    return Telescope(ovro_lwa_layout("core", radius_m=15), GaussianBeam(30), [40e6])


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="module")
def blocks(small_telescope):
    """Transfer blocks B_m of the 8-stand array (``tests/imaging_helpers.py``)."""
    from tests.imaging_helpers import transfer_blocks

    return transfer_blocks(small_telescope)
