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

Each pass is a run directory of its own, with its lock, fingerprints and per-chunk markers, so a
kill anywhere resumes where it stopped, bit-identically; recomputing a pass makes everything after
it stale (the prior's ``alm.zarr/alm`` is in each ``mmodes`` fingerprint). The transfer stage runs
once per pass: a pass costs about as much as the imaging stages of the run.
"""
from __future__ import annotations

import os

from mmflow.workflow.engine.prior_run import pass_directory
from mmflow.workflow.engine.runner import run_workflow
from mmflow.workflow.pipeline import PIPELINE

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
    stages from ``mmodes`` on; returns the run's summaries (each pass's under ``prior<k>/<stage>``)."""
    n = cfg.mmode.prior_passes
    if not n or only:
        return run_workflow(cfg, client, only, force, progress, log, pipeline)
    up = _upstream(cfg, pipeline)
    summaries = run_workflow(cfg, client, [st.name for st in up], force, progress, log, pipeline) if up else {}
    root = pass_directory(cfg.run.directory, 0).parent
    for k in range(n):
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
    rest = [st.name for st in pipeline if st.enabled(cfg) and st.name not in {u.name for u in up}]
    summaries.update(run_workflow(cfg, client, rest, force, progress, log, pipeline))
    return summaries
