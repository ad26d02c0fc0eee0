import os
from pathlib import Path

import numpy as np
import pytest

#: the suite's own cache (parsed IERS tables, numba's compiled kernels), inside the checkout's
#: .pytest_cache (git-ignored): the tests never write to the user's ~/.cache/mmflow
os.environ.setdefault("MMFLOW_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "mmflow"))


def _share_the_cores():
    """Each test process's thread budget: the usable cores divided among the processes running tests at
    once (pytest-xdist's workers; ``make test`` runs four on this two-core VM), for mmflow's kernels
    (``MMFLOW_THREADS``) and for BLAS, here (threadpoolctl) and in every process a test starts (the
    variables). Four processes of two threads each on two cores took the suite 15 min 14 s, of one
    thread each 13 min 50 s (docs/performance.md): OpenBLAS's threads spin while they wait. A variable
    already set is kept."""
    from mmflow.threads import usable_cores

    per = str(max(1, usable_cores() // max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))))
    for var in ("MMFLOW_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, per)
    from threadpoolctl import threadpool_limits

    threadpool_limits(int(os.environ["OPENBLAS_NUM_THREADS"]), user_api="blas")  # this process's BLAS, loaded


_share_the_cores()

#: the longest test files, longest first: started first, so that with ``-n 3 --dist loadfile
#: --no-loadscope-reorder`` (``make test``) no long file is left running alone at the end (a scheduling
#: hint; measured, docs/performance.md). Without ``--no-loadscope-reorder`` xdist sorts the files by
#: their number of tests and the one-test README tour (~3 min) started last.
LONGEST_FIRST = ("test_slurm_cluster.py", "test_readme.py", "test_plan_traced.py", "test_stokes_workflow.py",
                 "test_raw_day.py", "test_calibration_workflow.py", "test_four_correlation_peel.py",
                 "test_clean_stage.py", "test_calibration_ingest.py", "test_faults.py", "test_workflow.py",
                 "test_cluster.py", "test_independent_peel.py", "test_channel_blocks.py", "test_models_stage.py",
                 "test_plan.py")


def pytest_collection_modifyitems(config, items):
    """Tests in three tiers: ``tests/unit`` (kernels on in-memory arrays, ``make test-fast``),
    ``tests/workflow`` (stages and runs at small scale) and ``tests/acceptance`` (the README tour, the
    demos, faults, clusters, real files and matvis scans at scale), marked ``slow``
    (``pytest -m "not slow"`` leaves them out). The files of :data:`LONGEST_FIRST` run first."""
    for item in items:
        if "acceptance" in item.path.parts:
            item.add_marker(pytest.mark.slow)
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file's order kept


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
