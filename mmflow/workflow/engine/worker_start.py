"""What a local cluster's worker server imports once, before it forks each worker.

Importing this module imports every stage (:mod:`mmflow.workflow.pipeline`) and loads numba's
compiler runtime and the imaging kernels every imaging run calls (the Legendre recurrence and the
fringe kernel in both precisions) from numba's cache, compiling them on a machine's first run.
Each worker is then a fork that shares them, so no worker task bears numba's ~45 MB runtime start
(~0.5 s) or a compilation (~15 MB and 1-1.5 s per kernel, per worker, on a fresh installation), nor
astropy's time tables and formats (:func:`load_time_tables`):
a task's measured memory is its working set, as :mod:`mmflow.workflow.plan.planner` models it, and the
runtime sits in the worker's baseline (``WORKER_BASE_BYTES``). A job-queue cluster's workers import it
when they start (``--preload``, :data:`mmflow.workflow.engine.batch.WORKER_PRELOAD`); workers started any
other way (``dask worker`` by hand) load them in their first task instead; nothing else differs.

As a preload it also counts a job-queue worker's ``--lifetime`` from its job's start
(:func:`dask_setup`), so that the worker retires before the batch system's walltime however long
it took to start.
"""
import os
import time

import numpy as np

import mmflow.workflow.pipeline  # noqa: F401  (the stages, imported once for every worker)
from mmflow.mmode.fringe_kernels import sincos_turns
from mmflow.mmode.legendre import weighted_legendre_table
from mmflow.workflow.engine.batch import JOB_START_VAR


def load_compiled_kernels():
    """Call each imaging kernel once on a few values, in every precision the transfer stage uses."""
    theta = np.linspace(0.1, 3.0, 4)
    for dtype in (np.float32, np.float64):
        weighted_legendre_table(1, 4, theta, np.ones(4), dtype, 2)
        sincos_turns(np.linspace(0.0, 1.0, 4), dtype)


def load_time_tables():
    """Turn one time into a frame rotation and a sidereal angle, as the stages that place sources do
    (:func:`mmflow.sky.frames.rotation_matrix`, :func:`mmflow.sky.frames.apparent_sidereal_time`): astropy
    then loads its IERS and leap-second tables and its time formats once here. Its first time parse
    leaves reference cycles (the exceptions of its format guessing) whose frames hold their callers' frames
    and so the calling task's arrays until the next garbage collection: in a worker's first task that
    raised the 352-antenna array's first m-mode task to 96.7 MB traced, against 69.9 for the next ones."""
    from mmflow.sky.frames import apparent_sidereal_time, rotation_matrix  # deferred: astropy's coordinates

    rotation_matrix("icrs", "date", 2451545.0)
    apparent_sidereal_time(2451545.0, 0.0)


for _warm_up in (load_compiled_kernels, load_time_tables):
    try:
        _warm_up()
    except Exception:  # noqa: BLE001 -- a warm-up only: the first task that needs it reports its error
        pass


def lifetime_left(lifetime, job_start, now):
    """Seconds until a worker of lifetime ``lifetime`` (its ``--lifetime``, stagger drawn) retires when
    counted from its job's start ``job_start`` rather than from its own start: ``lifetime - (now -
    job_start)``, at least 0; None where either is unknown (dask's own count then stands)."""
    if not lifetime or job_start is None:
        return None
    return max(float(lifetime) - (now - job_start), 0.0)


def dask_setup(worker):
    """dask's preload hook: a worker in a batch job (the job script exports :data:`JOB_START_VAR`)
    retires ``lifetime`` after its job started, not after it started itself. dask's own timer, later,
    then finds the worker closed."""
    try:
        job_start = float(os.environ[JOB_START_VAR])
    except (KeyError, ValueError):
        return
    left = lifetime_left(getattr(worker, "lifetime", None), job_start, time.time())
    if left is not None:
        worker.io_loop.call_later(left, worker.close_gracefully, reason="worker-lifetime-reached")
