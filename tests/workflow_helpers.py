"""Small workflow configurations shared by the workflow tests."""
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zarr

from mmflow.errors import InputError
from mmflow.workflow.config.schema import load_config

#: the repository root
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEMO = os.path.join(ROOT, "workflows", "demo.yaml")

SMALL = [
    "run.keep=[]",  # the release of the m-modes as every workflow has it (the demo keeps them for the README)
    "telescope.radius_m=20",
    "observation.freqs_mhz=[40.0]",
    "observation.integration_s=344.6563620",
    "sky.diffuse=true",
    "sky.diffuse_lmax=16",
    "sky.quad_oversample=16",
    "mmode.lmax=24",
    "mmode.baseline_chunk=64",
    "transfer.baseline_chunk=32",
    "transfer.m_block=8",
    "products.nside=32",
    # the flux scale's 14-panel figure costs ~2 s a run; tests/acceptance/test_science_products.py covers it
    "products.flux_scale=false",
    "cluster.kind=synchronous",
]


def refused_problem(overrides, field, path=DEMO):
    """Load ``path`` with ``overrides``, expect the InputError, and return ``((what, field, problem,
    fix), error)`` for the problem it names for ``field`` (failing when it names none)."""
    with pytest.raises(InputError) as info:
        load_config(path, overrides)
    err = info.value
    lines = getattr(err, "problems", [(err.what, err.field, err.problem, err.fix)])
    hit = [ln for ln in lines if ln[1] == field]
    assert hit, f"no problem for field {field}: {lines}"
    return hit[0], err


def small_config(run_dir, *extra):
    return load_config("workflows/demo.yaml", SMALL + [f"run.directory={run_dir}", *extra])


def fork_run(src, dst, after):
    """``dst``: a copy of the run directory ``src`` with every stage after ``after`` forgotten and its
    outputs removed (:meth:`mmflow.workflow.engine.rundir.RunDir.reset_stage`), so that a run there
    recomputes them from ``src``'s stages up to ``after``. Stages are deterministic: this is the
    directory a fresh run of ``src``'s configuration leaves once ``after`` is complete."""
    import shutil

    from mmflow.workflow.pipeline import ORDER
    from mmflow.workflow.engine.rundir import RunDir

    shutil.copytree(src, dst)
    for stage in ORDER[ORDER.index(after) + 1:]:
        RunDir(dst).reset_stage(stage)
    return dst


def read_outputs(run_dir):
    """Every array a finished run produced (for bit-identical comparisons)."""
    out = {}
    for store in ("vis.zarr", "mmodes.zarr", "normal.zarr", "alm.zarr", "stokes.zarr"):
        if store == "stokes.zarr" and not (run_dir / store).exists():  # a Stokes-I run
            continue
        g = zarr.open_group(str(run_dir / store), mode="r")
        for name, arr in g.arrays():
            out[f"{store}/{name}"] = arr[:]
        for gname, sub in g.groups():
            for name, arr in sub.arrays():
                out[f"{store}/{gname}/{name}"] = arr[:]
    import healpy
    from astropy.io import fits as afits

    for fits in sorted((run_dir / "maps").glob("*.fits")):
        with afits.open(fits) as hdul:
            healpix = len(hdul) > 1 and hdul[1].header.get("PIXTYPE") == "HEALPIX"
            # every column (I, Q, U, V) of a HEALPix map; the image of any other (CLEAN's PSF stamps)
            out[fits.name] = healpy.read_map(str(fits), field=None) if healpix else np.array(hdul[0].data)
    return out


def assert_identical(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k], equal_nan=True), k


def interrupt_run(run_dir, stage, sig, extra=(), base=("workflows/demo.yaml", *SMALL)):
    """Start a CLI run (``mmflow run *base *extra``) in a subprocess and send ``sig`` once ``stage`` has
    finished its first chunk, and check that the signal is what ended it there.

    Fails (instead of "resuming" a run that never got to ``stage``) when the child exits before that
    point (refused, crashed or finished early), when ``stage`` was already complete when the signal was
    sent, or when the child did not end by the signal (SIGKILL: killed; SIGINT: KeyboardInterrupt, exit
    -2 or 130).
    """
    args = [sys.executable, "-m", "mmflow.cli", "run", *base, *extra, f"run.directory={run_dir}", "--no-progress"]
    env = dict(os.environ, MMFLOW_TASK_DELAY_S="0.2")
    # the child gets SIGINT's default action (Python's KeyboardInterrupt): a pytest-xdist worker
    # ignores SIGINT, and an ignored signal is inherited across exec
    proc = subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    marker_dir = run_dir / "_status" / stage
    deadline = time.time() + 120
    while (time.time() < deadline and proc.poll() is None
           and not (marker_dir.exists() and any(marker_dir.glob("[!_]*.done")))):
        time.sleep(0.05)
    if proc.poll() is not None:
        raise AssertionError(f"the run ended (exit {proc.returncode}) before stage {stage!r} finished a chunk:\n"
                             + proc.stderr.read().decode(errors="replace")[-2000:])
    if not any(marker_dir.glob("[!_]*.done")):
        proc.kill()
        proc.wait(timeout=60)
        raise AssertionError(f"stage {stage!r} finished no chunk in 120 s")
    complete_before = (marker_dir / "complete.json").exists()
    proc.send_signal(sig)
    proc.wait(timeout=60)
    proc.stderr.close()
    assert not complete_before, f"stage {stage!r} was already complete when {sig!r} was sent"
    ended_by = {signal.SIGKILL: {-signal.SIGKILL}, signal.SIGINT: {-signal.SIGINT, 130}}.get(sig, {-sig})
    assert proc.returncode in ended_by, f"the run exited {proc.returncode}, not by {sig!r}"
    assert not (run_dir / "_status" / "products" / "complete.json").exists()
