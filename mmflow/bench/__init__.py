"""``mmflow bench WHAT``: measured figures printed as JSON (never asserted as times in tests).

One module per subject: :mod:`.engine` (transfer, solve, simulate), :mod:`.workflow` (the
workflow's own costs: checksums, non-finite guards, per-stage times), :mod:`.calibrate`
(Stefcal and peeling), :mod:`.ingest` (ingest vs pyuvdata's read rate), :mod:`.gaps`
(least-squares m-modes of flagged data), :mod:`.clean` (PSF and CLEAN cycles), :mod:`.channel`
(one real channel through transfer, Gram and solve, per phase, beside the model's projection),
:mod:`.table1` (the paper array's resolution at the paper's fraction of modes), :mod:`.paper` (the
paper's channel end to end through the workflow, per stage, beside ``mmflow plan``), :mod:`.stokes`
(``transfer --stokes IQUV``: full-Stokes transfer + Gram against Stokes I), :mod:`.stokes_block` (the stokes
stage's block tasks at the paper's scale on a fraction of the baselines, beside its cost model).
"""
from __future__ import annotations

import importlib

MODULES = {"transfer": "engine", "solve": "engine", "simulate": "engine", "workflow": "workflow",
           "calibrate": "calibrate", "ingest": "ingest", "gaps": "gaps",
           "clean": "clean", "channel": "channel", "table1": "table1", "paper": "paper", "cluster": "cluster",
           "stokes-block": "stokes_block"}


def run(what, quick=False, **options):
    """Run one benchmark; ``options`` are passed on to benchmarks that take them (``channel``, ``paper``,
    ``ingest``)."""
    name = MODULES[what]
    if what == "transfer":  # --stokes IQUV: full Stokes against Stokes I (:mod:`.stokes`)
        name = "stokes" if options.pop("stokes", "I") == "IQUV" else name
    mod = importlib.import_module(f"mmflow.bench.{name}")
    return mod.run(what, quick=quick, **options)
