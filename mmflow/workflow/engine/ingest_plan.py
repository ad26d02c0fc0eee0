"""The workflow's ingest plan: :func:`mmflow.io.ingest.plan_ingest` of a configuration's ``input`` settings.

``io`` takes plain arguments; this is the one place that reads them from the configuration (the ingest
stage, the configuration checks, the planner and the benchmarks call it).
"""
from __future__ import annotations

from mmflow.io.ingest import ingest_time_chunk, plan_ingest


def ingest_plan(cfg):
    """The ingest plan of ``cfg.input`` (cached by :func:`mmflow.io.ingest.plan_ingest`). Units other than
    Jy / K sr are accepted only when ``calibrate.enabled``."""
    i = cfg.input
    want = cfg.observation.freqs_mhz
    return plan_ingest(i.path, i.format, i.on_bad_file, bool(cfg.calibrate.enabled),
                       None if want is None else tuple(want), int(i.average_channels), bool(i.cross_hands),
                       str(i.pol_convention))


def ingest_rows(cfg, store_path, row0, row1):
    """Ingest the rows ``row0..row1`` into ``store_path`` with ``cfg.input``'s format, non-finite policy and
    conjugation (:func:`mmflow.io.ingest.ingest_time_chunk`)."""
    i = cfg.input
    return ingest_time_chunk(store_path, row0, row1, fmt=i.format, nonfinite=i.nonfinite, conjugate=i.conjugate)
