"""An earlier run's map as the prior of the least-squares m-mode fit (``mmode.prior_run``).

Flagged time leaves directions of a baseline's m-modes that its own data do not measure
(long gaps on long baselines, ``docs/mmodes.md``). :func:`mmflow.mmode.gapfill.lsq_mmodes`
fills them from a prior: the m-modes ``B_m a_m`` of a map's model visibilities
(:func:`mmflow.mmode.gapfill.prior_mmodes`). Here that map is the solved ``alm.zarr`` (first
data split, Jy/sr, frame of date) of an earlier run of the same data: run once, then again
in a new directory with ``mmode.prior_run`` set to the first.

The earlier run must be finished (its ``solve`` stage complete) with the same ``lmax``, an
``mmax`` at least this run's, the same channels and the same epoch (the frame of date; 1 day
of precession is 0.14 arcsec). :func:`prior_run_problems` lists what does not fit, for the
configuration check (before any work) and for the ``mmodes`` stage's prepare (channels and
epoch of ingested data are known only there). ``alm.zarr`` is the stage's input file
(:func:`prior_files`): recomputing the earlier run makes this run's ``mmodes`` and every
later stage stale.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from mmflow.conventions import healpy_alm
from mmflow.errors import InputError
from mmflow.io.stores import open_checked
from mmflow.workflow.engine.rundir import RunDir
from mmflow.paths import expand_path
from mmflow.io.run_stores import STORES

FIELD = "mmode.prior_run"
ALM = STORES.alm
AUTO_RECORD = "prior_passes.json"
EPOCH_TOL_DAYS = 1.0  # precession over a day: 0.14 arcsec
RECIPE = "mmflow run CFG.yaml; mmflow run CFG.yaml run.directory=RUN-pass1 mmode.prior_run=RUN"


@dataclass
class PriorRun:
    """What an earlier run offers as a prior: its alm's shape, channels and epoch."""

    path: Path
    lmax: int
    mmax: int
    n_split: int
    freqs_hz: np.ndarray
    epoch_jd: float


def resolve(path):
    return Path(expand_path(path)).absolute()


def pass_directory(run_directory, k):
    """Where prior pass ``k`` of a run with ``mmode.prior_passes`` lives: ``RUN/prior<k>``."""
    return resolve(run_directory) / f"prior{k}"


def auto_record(run_directory):
    """``RUN/prior_passes.json``: what ``mmode.prior_passes: auto`` decided (:mod:`mmflow.workflow.engine.passes`)."""
    return resolve(run_directory) / AUTO_RECORD


def auto_passes(run_directory):
    """The passes ``mmode.prior_passes: auto`` made for a run (0 where it has made no decision yet)."""
    try:
        return int(json.loads(auto_record(run_directory).read_text())["passes"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def effective_prior(mm, run_directory):
    """The run whose map is a run's prior: ``mmode.prior_run``, or with ``mmode.prior_passes = n`` the
    run's last automatic pass ``RUN/prior<n-1>`` (:mod:`mmflow.workflow.engine.passes`; ``auto``: the passes
    it recorded); None: no prior.

    ``mm``: the ``mmode`` section; ``run_directory``: the run's directory (where its passes live)."""
    if mm.prior_run is not None:
        return mm.prior_run
    n = auto_passes(run_directory) if mm.prior_passes == "auto" else mm.prior_passes
    if n:
        return str(pass_directory(run_directory, n - 1))
    return None


def prior_files(cfg):
    """The earlier run's solved alm array, ``alm.zarr/alm`` (digested into the ``mmodes`` stage's
    fingerprint), or none. The array only: the group's attributes are restamped whenever that run
    passes its solve stage, and a setting that leaves the alm alone must not make this run stale."""
    p = effective_prior(cfg.mmode, cfg.run.directory)
    if not p:
        return []
    alm = resolve(p) / ALM / STORES.alm.alm
    if cfg.mmode.prior_passes and not alm.exists():
        return []  # the run's own pass, not made yet: the stages before it run first (mmflow.workflow.engine.passes)
    return [str(alm)]


def _describe(path):
    """A :class:`PriorRun`, or ``(problem, fix)`` when ``path`` holds no finished run."""
    again = f"finish that run first (mmflow run {path / 'config.yaml'}), or give another run directory"
    if not path.is_dir():
        return None, ("no such run directory", "give the run.directory of a finished earlier run of the same "
                      f"data ({RECIPE})")
    status = RunDir(path).stage_status("solve")
    if status is None or not status["complete"] or not (path / ALM).is_dir():
        return None, (f"holds no finished {ALM} (its solve stage has not completed)", again)
    try:
        alm = zarr.open_group(str(path / ALM), mode="r")[STORES.alm.alm]
        vis = zarr.open_group(str(path / STORES.vis), mode="r")
        freqs, epoch = np.asarray(vis[STORES.vis.freqs_hz][:], float), float(vis.attrs["epoch_jd"])
    except (KeyError, OSError, ValueError) as exc:
        return None, (f"its {ALM} or vis.zarr cannot be read ({exc})", again)
    n_split, nf, m1, l1 = alm.shape
    return PriorRun(path, l1 - 1, m1 - 1, n_split, freqs, epoch), None


def prior_run_problems(prior_run, lmax, mmax, run_dir, freqs_hz=None, epoch_jd=None):
    """``[(problem, fix)]`` of ``prior_run`` as the prior of a run (empty: usable).

    Parameters
    ----------
    prior_run : str
        ``mmode.prior_run``.
    lmax, mmax : int
        This run's ``mmode.lmax`` and m-mode ``mmax``.
    run_dir : str
        This run's ``run.directory`` (the prior cannot be the run it feeds).
    freqs_hz, epoch_jd : optional
        This run's channels and epoch, where known (simulated data: from the configuration;
        ingested data: from ``vis.zarr`` in the stage's prepare).
    """
    path = resolve(prior_run)
    if path == resolve(run_dir):
        return [("is this run's own directory: the run would overwrite the map that feeds it",
                 f"run the second pass in a new directory: {RECIPE}")]
    pr, problem = _describe(path)
    if problem:
        return [problem]
    out = []
    if pr.lmax != lmax:
        out.append((f"its {ALM} has lmax {pr.lmax}, this run mmode.lmax {lmax}",
                    f"set mmode.lmax={pr.lmax}, or give a prior run imaged at lmax {lmax}"))
    if pr.mmax < mmax:
        out.append((f"its {ALM} has mmax {pr.mmax} < this run's {mmax}: m > {pr.mmax} would get no prior",
                    f"set mmode.mmax <= {pr.mmax}, or give a prior run with mmax >= {mmax}"))
    if freqs_hz is not None:
        f = np.asarray(freqs_hz, float)
        if f.shape != pr.freqs_hz.shape or not np.allclose(f, pr.freqs_hz, rtol=0, atol=1.0):
            out.append((f"its channels {np.round(pr.freqs_hz / 1e6, 6).tolist()} MHz are not this run's "
                        f"{np.round(f / 1e6, 6).tolist()} MHz", "give a prior run of the same data "
                        "(same observation.freqs_mhz or input files)"))
    if epoch_jd is not None and abs(epoch_jd - pr.epoch_jd) > EPOCH_TOL_DAYS:
        out.append((f"its epoch JD {pr.epoch_jd:.5f} is {abs(epoch_jd - pr.epoch_jd):.1f} days from this run's "
                    f"{epoch_jd:.5f}: its map is in another frame of date",
                    "give a prior run of the same data (same observation.epoch_jd or input files)"))
    return out


def check_prior_run(prior_run, lmax, mmax, run_dir, freqs_hz, epoch_jd):
    """Raise :class:`~mmflow.errors.InputError` for the first problem of :func:`prior_run_problems`."""
    problems = prior_run_problems(prior_run, lmax, mmax, run_dir, freqs_hz, epoch_jd)
    if problems:
        problem, fix = problems[0]
        raise InputError(str(resolve(prior_run)), FIELD, problem, fix)


def read_prior_alm(prior_run, fi, lmax):
    """The earlier run's first-split alm of channel ``fi``, healpy layout (Jy/sr, frame of date).

    Chunks are checked against the earlier run's ``solve`` records as they are read.
    """
    path = resolve(prior_run)
    g = open_checked(str(path), ALM, "r", RunDir(path).chunk_index("solve"), "solve")
    return healpy_alm(g[STORES.alm.alm][0, fi], lmax)
