import os

import numpy as np
import pytest

os.environ.setdefault("MMFLOW_THREADS", "2")


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
