"""Prior passes inside one run (``mmode.prior_passes``): flagged time filled from the run's own map.

Flagged blocks leave directions of each baseline's m-mode fit that only a map knows
(:mod:`mmflow.workflow.engine.prior_run`). With ``mmode.prior_passes = n`` one ``mmflow run`` does what
the two-run recipe did by hand:

1. the stages before ``mmodes`` (ingest or simulate, calibrate, peel, terrestrial) run in the
   run directory ``RUN``;
2. pass ``k = 0 .. n-1`` runs ``mmodes -> transfer -> normal -> solve`` in ``RUN/prior<k>``, whose
   stores and records of those earlier stages are symbolic links to ``RUN``'s (nothing is copied
   or recomputed); pass 0 fits the m-modes by least squares alone, pass ``k > 0`` with pass
   ``k - 1``'s map as the prior;
3. the rest of the pipeline runs in ``RUN`` with the last pass's map as its prior.

``auto`` (the default) chooses ``n``: 0 where no baseline's flagged time leaves a gap longer than its
band limit bridges (:func:`unbridged_baselines`; the run is then the run without passes), else passes
until the map changes by less than ``mmode.prior_tolerance`` (:func:`map_change`), at most
``mmode.prior_max_passes``; the count is recorded in ``RUN/prior_passes.json``
(:func:`mmflow.workflow.engine.prior_run.auto_passes`). ``mmode.prior_run`` (an earlier run as the prior)
makes no pass.

Each pass is a run directory of its own, with its lock, fingerprints and per-chunk markers, so a
kill anywhere resumes where it stopped, bit-identically; recomputing a pass makes everything after
it stale (the prior's ``alm.zarr/alm`` is in each ``mmodes`` fingerprint). The transfer stage runs
once per pass: a pass costs about as much as the imaging stages of the run.
"""
from __future__ import annotations

import json
import os

import numpy as np
import zarr

from mmflow.errors import MmflowError
from mmflow.io.polarization import stokes_i
from mmflow.mmode.gapfill import unbridged_gaps
from mmflow.mmode.transform import bin_occupancy
from mmflow.workflow.engine.context import run_telescope
from mmflow.workflow.engine.geometry import fit_bins, n_bins_of
from mmflow.workflow.engine.prior_run import ALM, auto_record, pass_directory, resolve
from mmflow.workflow.engine.runner import run_workflow
from mmflow.workflow.pipeline import PIPELINE
from mmflow.io.run_stores import STORES

#: the stages of a prior pass: from the m-modes to the solved map
PASS_STAGES = ("mmodes", "transfer", "normal", "solve")


def _upstream(cfg, pipeline):
    """The enabled stages before ``mmodes`` (their stores and records are shared with the passes)."""
    return [st for st in pipeline.stage("mmodes").upstream if st.enabled(cfg)]


def _link(target, link):
    """``link`` -> ``target`` (a relative symlink), kept when it already points there."""
    rel = os.path.relpath(target, link.parent)
    if link.is_symlink() and os.readlink(link) == rel:
        return
    if link.exists() or link.is_symlink():
        raise FileExistsError(f"{link} exists and is not mmflow's link to {target}: remove it, or use a new "
                              "run.directory")
    link.parent.mkdir(parents=True, exist_ok=True)
    os.symlink(rel, link)


def pass_config(cfg, k):
    """The configuration of prior pass ``k``: its own directory, the pass before it as its prior."""
    prior = str(pass_directory(cfg.run.directory, k - 1)) if k else None
    mm = cfg.mmode.model_copy(update={"prior_passes": 0, "prior_run": prior})
    run = cfg.run.model_copy(update={"directory": str(pass_directory(cfg.run.directory, k))})
    return cfg.model_copy(update={"mmode": mm, "run": run})


def run_with_passes(cfg, client=None, only=None, force=False, progress=True, log=print, pipeline=PIPELINE):
    """:func:`mmflow.workflow.engine.runner.run_workflow`, with ``mmode.prior_passes`` passes before the
    stages from ``mmodes`` on; returns the run's summaries (each pass's under ``prior<k>/<stage>``).

    ``auto`` (the default; :func:`unbridged_baselines` decides): no pass where no baseline has a gap its band
    limit cannot bridge (the run is the run without passes); else passes ``k = 0, 1, ...`` until the map
    changes by less than ``mmode.prior_tolerance`` (:func:`map_change`), at most ``mmode.prior_max_passes``,
    the count recorded in ``RUN/prior_passes.json`` for the stages that take the last pass's map."""
    mm = cfg.mmode
    auto = mm.prior_passes == "auto"
    n = 0 if mm.prior_run is not None else mm.prior_max_passes if auto else mm.prior_passes
    if only or not n:
        return run_workflow(cfg, client, only, force, progress, log, pipeline)
    up = _upstream(cfg, pipeline)
    planned = [st.name for st in pipeline if st.enabled(cfg)]  # checked as one run, before any work
    summaries = run_workflow(cfg, client, [st.name for st in up], force, progress, log, pipeline,
                             planned=planned) if up else {}
    need = unbridged_baselines(cfg, log) if auto else None
    root = pass_directory(cfg.run.directory, 0).parent
    k = 0
    while need != 0 and k < n:
        pcfg = pass_config(cfg, k)
        pdir = pass_directory(cfg.run.directory, k)
        for st in up:  # the earlier stages' stores and records, shared
            for out in st.outputs:
                _link(root / out, pdir / out)
            _link(root / "_status" / st.name, pdir / "_status" / st.name)
        log(f"[prior pass {k}] {' -> '.join(PASS_STAGES)} in {pdir}"
            + (f" with pass {k - 1}'s map as the prior" if k else " (least squares alone)"))
        done = run_workflow(pcfg, client, list(PASS_STAGES), force, progress, log, pipeline)
        summaries.update({f"prior{k}/{name}": s for name, s in done.items()})
        k += 1
        if auto and k > 1:
            change = map_change(pass_directory(cfg.run.directory, k - 2), pdir)
            log(f"[prior pass {k - 1}] the map changed by {change:.4f} (mmode.prior_tolerance {mm.prior_tolerance:g})")
            if change < mm.prior_tolerance:
                break
    if auto:
        _write_json(auto_record(cfg.run.directory), {"passes": k, "baselines_with_unbridged_gaps": need})
    rest = [st.name for st in pipeline if st.enabled(cfg) and st.name not in {u.name for u in up}]
    summaries.update(run_workflow(cfg, client, rest, force, progress, log, pipeline))
    return summaries


def _write_json(path, value):
    """``value`` as JSON at ``path``, replaced whole (a kill leaves the old record or the new)."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(value))
    os.replace(tmp, path)


def map_change(before, after):
    """``||a_k - a_(k-1)|| / ||a_k||`` of the solved alm (first split, every channel) of two passes' run
    directories: how much a pass changed the map."""
    a0, a1 = (zarr.open_group(str(d / ALM), mode="r")[STORES.alm.alm][0] for d in (before, after))
    return float(np.linalg.norm(a1 - a0) / max(np.linalg.norm(a1), np.finfo(float).tiny))


def unbridged_baselines(cfg, log=print):
    """Baseline fits (per channel) whose flagged time leaves a gap their band limit cannot bridge
    (:func:`mmflow.mmode.gapfill.unbridged_gaps`: longer than ``N / (2 M_b + 1)`` sidereal bins), from
    the weights of ``RUN/vis.zarr`` binned as the ``mmodes`` stage bins them (Stokes I: flagged where
    either hand is; the flags of the input, before calibration's). Reads the weights one baseline chunk at
    a time; 0: ``auto`` makes no prior pass. Where the run has released the weights (once ``mmodes`` had
    read them: :data:`mmflow.io.run_stores.RELEASED_ARRAYS`), the count recorded when they were read (the
    weights are released only after that record, and recomputed bit for bit before any stage reads them)."""
    run = resolve(cfg.run.directory)
    vis = zarr.open_group(str(run / STORES.vis), mode="r")
    if STORES.vis.weights not in vis:
        try:
            return int(json.loads(auto_record(cfg.run.directory).read_text())["baselines_with_unbridged_gaps"])
        except (OSError, ValueError, KeyError, TypeError):
            raise MmflowError(f"{run / STORES.vis} holds no weights (released once the mmodes stage had read them) "
                              "and the run recorded no count of unbridged baselines. Fix: set "
                              "mmode.prior_passes to a number (0: none), or keep them: run.keep=[vis.zarr]") from None
    lst = vis[STORES.vis.lst][:]
    good_t = np.isfinite(lst)
    n_bins = n_bins_of(cfg, vis.attrs["integration_s"])
    half = fit_bins(cfg.mmode.splits, n_bins) // 2
    tel, freqs, pairs = run_telescope(cfg, run), vis[STORES.vis.freqs_hz][:], vis[STORES.vis.pairs][:]
    weights = vis[STORES.vis.weights]
    step = weights.chunks[1]
    count = 0
    for start in range(0, weights.shape[1], step):
        cols = slice(start, min(weights.shape[1], start + step))
        _, w = stokes_i(*(weights[:, cols][good_t],) * 2)  # (time, bl, freq)
        filled = bin_occupancy(lst[good_t], w > 0, n_bins)
        for fi, f in enumerate(freqs):
            count += int(unbridged_gaps(filled[:, :, fi], tel.baseline_lmax(f, half, pairs[cols])).sum())
    log(f"[prior passes] auto: {count} baseline fit(s) with a gap longer than the band limit bridges"
        + (": no prior pass" if not count else ": prior passes until the map settles"))
    return count
