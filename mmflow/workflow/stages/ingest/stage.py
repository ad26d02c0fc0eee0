"""The ``ingest`` stage: UVH5 / uvfits / MeasurementSet files read with pyuvdata into ``vis.zarr``.

Its ``check`` runs the plan (every file's metadata and checks, :func:`mmflow.io.ingest.plan_ingest`)
before the run does any work (and its ``scan``, when the stage has tasks to do, refuses unflagged
NaN/inf samples: :func:`mmflow.io.ingest.refuse_nonfinite`), and, when the run goes on to the m-mode stage, refuses an
observation whose integrations cannot cover ``mmode.min_coverage`` of the sidereal bins (a single
13 s snapshot, say): m-modes need a drift scan over (most of) a sidereal day.
"""
from __future__ import annotations

import glob

from mmflow.errors import CoverageError
from mmflow.io.ingest import plan_arrays, refuse_nonfinite, sidereal_coverage
from mmflow.workflow.engine.ingest_plan import ingest_plan, ingest_rows
from mmflow.io.run_stores import STORES, vis_store
from mmflow.workflow.engine.chunking import TIME_CHUNK, chunk_rows, time_keys
from mmflow.workflow.engine.data_stage import VIS_ARRAYS, layout_attrs, write_autos
from mmflow.workflow.engine.geometry import n_bins_of
from mmflow.workflow.stages.ingest.cost import COST
from mmflow.workflow.stages.base import Stage

CROSS_ARRAYS = (STORES.vis.vis_cross, STORES.vis.weights_cross)


def input_files(cfg):
    """The files ``input.path`` names (a glob or one path), as the ingest plan sees them."""
    pattern = cfg.input.path
    if not pattern:
        return []
    return sorted(glob.glob(pattern)) or ([pattern] if "*" not in pattern else [])


def _ingest_check(cfg, running):
    plan = ingest_plan(cfg)
    if "mmodes" not in running:
        return
    n_bins = n_bins_of(cfg, plan.integration_s)
    covered = sidereal_coverage(plan, n_bins)
    if covered < cfg.mmode.min_coverage:
        span = plan.n_time * plan.integration_s
        raise CoverageError(cfg.input.path, "input.path",
                         f"{len(plan.files)} file(s) hold {plan.n_time} integration(s) of {plan.integration_s:g} s "
                         f"({span / 60:.1f} min): {covered:.2%} of the {n_bins} sidereal bins, where m-modes need "
                         f"mmode.min_coverage={cfg.mmode.min_coverage:g} of a sidereal day",
                         "point input.path at a drift scan over a sidereal day (e.g. a directory of one file per "
                         "integration: input.path='/data/day/*.ms'), or run only the stages before the m-modes "
                         "(`mmflow ingest`, `mmflow calibrate`)")


def _ingest_scan(cfg):
    """Unflagged NaN/inf samples refused before any task (``input.nonfinite=error``; with ``flag`` the
    tasks flag and count them)."""
    if cfg.input.nonfinite == "error":
        refuse_nonfinite(ingest_plan(cfg), cfg.input.format)


def _ingest_prepare(ctx):
    plan = ingest_plan(ctx.cfg)
    width = getattr(plan, "channel_width_hz", None)
    attrs = dict(
        layout_attrs(plan.layout),
        source="ingest",
        epoch_jd=plan.epoch_jd,
        files=list(plan.files),
        pols=plan.pols,
        cross_pols=plan.cross_pols,
        pol_convention=plan.file_info[0]["pol_convention_used"],
        pol_factor=plan.file_info[0]["pol_factor"],
        skipped_files=list(plan.skipped),
        integration_s=plan.integration_s,
        channel_width_hz=float(width) if width is not None else ctx.cfg.observation.channel_width_khz * 1e3,
        ingest_file_info=plan.file_info,
    )
    ctx.create(vis_store(plan.n_time, plan.pairs, plan.freqs_hz, plan.layout.enu, attrs, TIME_CHUNK,
                         ctx.cfg.mmode.baseline_chunk, plan_arrays(plan)))
    return time_keys(plan.n_time)


def _ingest_task(ctx, key):
    g = ctx.open(STORES.vis, mode="r+")
    t0, t1 = chunk_rows(key, g[STORES.vis.lst].shape[0])
    info = ingest_rows(ctx.cfg, ctx.run.store(STORES.vis), t0, t1)
    rows = (slice(t0, t1),)
    for name in VIS_ARRAYS + tuple(CROSS_ARRAYS if STORES.vis.vis_cross in g else ()):  # ingest writes the rows itself
        ctx.ledger.record(g[name], rows)
    write_autos(ctx, g, rows, g[STORES.vis.vis][t0:t1], g[STORES.vis.weights][t0:t1])
    return info


STAGE = Stage(
    "ingest",
    ("input", "mmode.baseline_chunk", "observation.channel_width_khz", "observation.freqs_mhz", "calibrate.enabled"),
    (),
    (STORES.vis,),
    _ingest_prepare,
    _ingest_task,
    enabled=lambda cfg: cfg.source == "ingest",
    files=input_files,
    check=_ingest_check,
    scan=_ingest_scan,
    counters=("fully_flagged_integrations", "nonfinite_flagged"),
    description="read UVH5 / uvfits / MS files with pyuvdata, fanned out over time chunks of files",
    cost=COST,
    recomputable=False,  # vis.zarr holds the files' data whole: the files may be gone on a rerun
)
