"""``mmflow plan``: what a run will need, per stage, before any work.

For every enabled stage the plan gives the number of tasks, the memory of its largest task, the
bytes of the stores it writes and a time estimate. Each comes from a model of the stage's work
(:func:`stage_work`): the task's working set ``W`` (bytes of the arrays a task holds: its time
chunk of visibilities, its baseline chunk over the day, its Gram accumulators, its m block) and
its work units ``U`` (visibility-samples x sources, baselines x sum_m (lmax_b - m + 1)^2, ...),
and from per-stage constants fitted to measured runs (:mod:`mmflow.workflow.plan.fit`, kept in
``plan/costs.json`` beside this module)::

    task memory  = a_s W + b_s                      (bytes above the worker's baseline)
    task seconds = (c_s U + d_s) * peak_ref / peak  (peak: this machine's SGEMM GFLOP/s now)

Store sizes are the declared stores' uncompressed bytes (:attr:`mmflow.io.stores.StoreSpec.nbytes`
of the same :mod:`mmflow.io.run_stores` declarations the stages create), an upper bound of the
disk they take (zarr compresses noise-like data by a few percent only).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mmflow.conventions import SPEED_OF_LIGHT, FULL_STOKES, SIDEREAL_DAY_S, is_full_stokes, m_blocks
from mmflow.errors import InputError
from mmflow.imaging.maps import default_nside
from mmflow.io import run_stores as rs
from mmflow.io.ingest import plan_ingest
from mmflow.machine import gemm_gflops
from mmflow.mmode.engine import plan_chunks, plan_groups
from mmflow.mmode.polarised_transfer import FOURIER_BUDGET_BYTES
from mmflow.mmode.transfer import fringe_bandlimit
from mmflow.simulate.drift_modes import n_samples
from mmflow.simulate.scene import diffuse_quad_lmax, feed_columns
from mmflow.simulate.visibilities import gauss_legendre_shape
from mmflow.workflow.engine.chunking import TIME_CHUNK
from mmflow.workflow.engine.context import build_telescope
from mmflow.workflow.engine.geometry import DIFFUSE_SAMPLE_BLOCK, interpolates_diffuse
from mmflow.workflow.pipeline import PIPELINE
from mmflow.paths import expand_path

COSTS_FILE = Path(__file__).with_name("costs.json")
#: A worker process's resident memory before any task (interpreter, numpy, dask, zarr, pyuvdata, the stages;
#: a local worker also numba's runtime and the imaging kernels: mmflow.workflow.engine.worker_start; measured 0.19 GB).
WORKER_BASE_BYTES = 0.35e9
LCURVE_POINTS = 200  # eps values of an L-curve (alm.zarr eps_grid)
PSF_DECLINATIONS = 16  # declinations of CLEAN's PSF table
#: CLEAN's major cycles are data-dependent (until the threshold): the plan assumes this many
EXPECTED_CLEAN_CYCLES = 40


@dataclass(frozen=True)
class Geometry:
    """The sizes every stage's work follows from (integrations, baselines, channels, ...)."""

    n_time: int
    n_ant: int
    n_bl: int
    n_freq: int
    n_pol: int
    lmax: int
    mmax: int
    m_block: int
    n_split: int
    mmode_chunk: int
    gram_itemsize: int
    transfer_units: tuple  # per channel, per baseline group: sum_b sum_m (lmax_b - m + 1)^2 (Gram work)
    transfer_workspace: float  # bytes of one transfer task's grid tables and ring-Fourier workspace
    n_sky_points: int = 0  # points the simulator sums per integration (sources; the diffuse grid if not interpolated)
    n_diffuse_points: int = 0  # the diffuse sky's quadrature grid, summed at diffuse_samples sidereal angles
    diffuse_samples: int = 0  # sidereal angles of an interpolated diffuse sky (0: none)
    n_feed_columns: int = 1  # simulated through each feed's power beam (2) or one beam (1)

    @property
    def n_groups(self):
        """Baseline groups of the transfer stage (partial normal equations per channel)."""
        return max(len(u) for u in self.transfer_units)

    @property
    def gram_dtype(self):
        return "complex64" if self.gram_itemsize == 8 else "complex128"
    n_cal_sources: int = 0
    cal_screen_rounds: int = 0  # alternations of gains and screens (0: no calibrate.screen_sources)
    n_peel_sources: int = 0
    cal_interval: int = 0  # integrations per calibration solution
    n_models: int = 0
    npix: int = 0
    clean_cycles: int = 0


@dataclass
class StageEstimate:
    """One stage's plan: tasks, the largest task's working set and work, stores and estimates."""

    stage: str
    tasks: int
    working_set_bytes: float
    units_per_task: float
    store_bytes: int
    task_bytes: float = 0.0  # predicted peak memory of the largest task above the worker baseline
    seconds: float = 0.0  # predicted wall time of the stage on the cluster
    notes: list = field(default_factory=list)


def _transfer_plan(tel, freq_hz, cfg, mmax):
    """Per baseline group of one channel (the transfer stage's own :func:`plan_chunks` and
    :func:`plan_groups`) its Gram work ``sum_chunks n_c sum_{m <= lmax_c} (lmax_c - m + 1)^2``, and the
    workspace of a task: float tables ``n_theta / 2 x (lmax + 1)(lmax + 2) / 2`` of the grid exact to
    ``lmax + fringe band limit`` (:func:`mmflow.mmode.transfer.make_grid`) and the ring-Fourier
    buffers ``2 x (mmax + 1) x n_theta / 2 x 2 n_chunk`` complex of the longest baselines' chunk."""
    t = cfg.transfer
    lmax = cfg.mmode.lmax
    chunks, _ = plan_chunks(tel, freq_hz, lmax, t.baseline_chunk, t.per_baseline_lmax)
    units = []
    for group in plan_groups(chunks, t.groups):
        units.append(sum(len(c.index) * _gram_work(c.lmax, mmax) for c in group))
    b = np.linalg.norm(tel.baselines_enu(), axis=1).max() * freq_hz / SPEED_OF_LIGHT
    n_theta = (lmax + int(fringe_bandlimit(np.array([b]), tel.beam.lmax_hint))) // 2 + 2
    real = 4 if t.dtype == "float32" else 8
    tables = n_theta / 2 * (lmax + 1) * (lmax + 2) / 2 * real
    fourier = 2 * (mmax + 1) * n_theta / 2 * 2 * t.baseline_chunk * 2 * real
    return tuple(units), tables + fourier


def _gram_work(lmax_c, mmax):
    """``sum_{m <= min(mmax, lmax_c)} (lmax_c - m + 1)^2``: one baseline's Gram updates."""
    n = np.arange(lmax_c - min(mmax, lmax_c) + 1, lmax_c + 2, dtype=float)
    return float(np.sum(n * n))


def _block_sum(lmax, mmax, m_block, power):
    """Largest ``sum_{m in block} (lmax - m + 1)^power`` over the m blocks (the first block)."""
    return max(float(sum((lmax - m + 1) ** power for m in range(m0, m1))) for m0, m1 in m_blocks(mmax, m_block))


def stage_work(stage, g, cfg):
    """``(tasks, W, U, store_specs)`` of one stage: its task count, the largest task's working set
    (bytes), its work units and the stores it writes (StoreSpecs), from the geometry alone."""
    T = min(TIME_CHUNK, g.n_time)
    n_tchunk = -(-g.n_time // TIME_CHUNK)
    vis_task = T * g.n_bl * g.n_freq * g.n_pol * 12.0  # complex64 visibilities + float32 weights
    vis_spec = rs.vis_store(g.n_time, np.zeros((g.n_bl, 2), int), np.zeros(g.n_freq), np.zeros((g.n_ant, 3)),
                            {"pols": ["p"] * g.n_pol}, TIME_CHUNK, g.mmode_chunk)
    if stage in ("simulate", "ingest"):
        units = T * g.n_bl * g.n_freq * (g.n_sky_points if stage == "simulate" else g.n_pol)
        w = vis_task
        if stage == "ingest":
            return n_tchunk, w, units, [vis_spec]
        # one channel at a time: ~10 complex128 (time, bl, pol) temporaries (drift scans, corruptions, noise;
        w += T * g.n_bl * g.n_pol * 160.0  # measured 2.8 GB at 256 antennas: docs/planning.md)
        if not g.diffuse_samples:
            return n_tchunk, w, units, [vis_spec]
        # an interpolated diffuse sky: first its direct sums at the sampled angles (DIFFUSE_SAMPLE_BLOCK a task:
        # their time is diffuse_sum_seconds'), then per time chunk its samples, their modes and their evaluation
        # at the chunk's integrations (the units: the time chunks')
        n_d = g.n_freq * -(-g.diffuse_samples // DIFFUSE_SAMPLE_BLOCK)
        w += g.diffuse_samples * g.n_bl * g.n_feed_columns * 32.0 + T * g.n_bl * g.n_feed_columns * 16.0
        spec = rs.diffuse_store(g.n_freq, g.diffuse_samples, g.n_bl, g.n_feed_columns, DIFFUSE_SAMPLE_BLOCK)
        return n_tchunk + n_d, w, units, [vis_spec, spec]
    if stage == "calibrate":
        L = max(1, min(g.cal_interval or g.n_time, g.n_time))
        n_int = -(-g.n_time // L) if cfg.calibrate.solint_s else 1  # null: one solve, on the track
        w = L * g.n_bl * g.n_pol * (12.0 + 16.0 * max(1, g.n_cal_sources))
        if g.cal_screen_rounds:  # the screened model, the masked data and weights; a batch's antenna matrices
            w += L * g.n_bl * g.n_pol * 56.0 + 6 * 16 * 16.0 * g.n_pol * g.n_ant ** 2
        spec = rs.gains_store(n_int, g.n_freq, g.n_ant, g.n_pol, g.n_time, np.zeros((n_int, 2), int),
                              np.zeros((n_int, 2), int), {}, n_src=max(1, g.n_cal_sources))
        # each screen round costs ~4 catalogue solves: a gain solve and the screen fits' antenna matrices
        # (`mmflow bench calibrate`, gains_screened; docs/calibration.md)
        units = L * g.n_bl * g.n_pol * max(1, g.n_cal_sources) * (1 + 4 * g.cal_screen_rounds)
        return n_int * g.n_freq, w, units, [spec]
    if stage == "models":
        return max(1, g.n_models) * g.n_freq, vis_task, g.n_time * g.n_bl, []
    if stage == "peel":
        n_src = max(1, g.n_peel_sources)
        # its channel's corrected block (complex128 + float64), the sources' models (complex64, one for both
        # hands) and a batch's antenna matrices (data, weights, residual and the models: 16 integrations x hands)
        w = T * g.n_bl * (24.0 * g.n_pol + 8.0 * n_src) + (n_src + 3) * 16 * g.n_pol * g.n_ant ** 2 * 8.0
        spec = rs.peel_store(g.n_time, g.n_freq, n_src, g.n_ant, g.n_pol, TIME_CHUNK, {})
        return n_tchunk * g.n_freq, w, T * g.n_bl * g.n_pol * n_src, [spec]
    if stage == "terrestrial":  # a task per channel and time chunk (both phases), reading its channel
        comp = cfg.terrestrial.components
        spec = rs.terrestrial_store(n_tchunk, g.n_time, g.n_freq, g.n_bl, comp, g.n_ant, g.n_pol, TIME_CHUNK)
        return 2 * n_tchunk * g.n_freq, vis_task / g.n_freq, T * g.n_bl * g.n_pol, [spec]
    if stage == "mmodes":
        bc = min(g.mmode_chunk, g.n_bl)
        # the corrected block (complex128 + float64) of every integration, and the peel stage's correction
        # of one channel on read: the subtracted sources' coherencies, five (time, bl, pol) complex
        # temporaries and the sources' per-antenna DD gains, read and copied (measured: 0.75 GB at 6,628
        # integrations and 64 antennas, 1.22 GB at 256: docs/planning.md)
        n_sub = len(cfg.peel.sources) if cfg.peel.enabled else 0
        per_time = bc * g.n_freq * g.n_pol * 24.0
        if n_sub:
            per_time += bc * 16.0 * (n_sub + 5 * g.n_pol) + 32.0 * n_sub * g.n_ant * g.n_pol
        w = g.n_time * per_time + g.n_split * g.n_freq * (g.mmax + 1) * 2 * bc * 16.0
        spec = rs.mmodes_store(g.n_split, g.n_freq, g.mmax, g.n_bl, g.mmode_chunk, {},
                               len(FULL_STOKES) if is_full_stokes(cfg.imaging.stokes) else 0)
        return -(-g.n_bl // bc), w, g.n_time * bc * g.n_freq * g.n_pol, [spec]
    if stage == "transfer":
        gram = _gram_bytes(g.lmax, g.mmax, g.gram_itemsize) + g.transfer_workspace
        per_group = max(max(u) for u in g.transfer_units)
        spec = rs.partials_store(g.n_freq, g.n_groups, g.lmax, g.mmax, g.m_block, g.n_split, g.gram_dtype)
        out = [spec]
        if cfg.transfer.mode == "store":
            out.append(rs.transfer_store(g.n_freq, g.n_bl, g.lmax, g.mmax, cfg.transfer.baseline_chunk,
                                         g.gram_dtype, [np.zeros(g.n_bl, int)] * g.n_freq))
        return sum(len(u) for u in g.transfer_units), gram, per_group, out
    n_mb = len(m_blocks(g.mmax, g.m_block))
    blk2 = _block_sum(g.lmax, g.mmax, g.m_block, 2)
    if stage == "normal":
        spec = rs.normal_store(g.n_freq, g.lmax, g.mmax, g.m_block, g.n_split, g.gram_dtype)
        return g.n_freq * n_mb, blk2 * 16.0, blk2 * g.n_groups, [spec]
    if stage == "solve":
        spec = rs.alm_store(g.n_freq, g.lmax, g.mmax, g.m_block, g.n_split, np.zeros(LCURVE_POINTS))
        return g.n_freq * n_mb, blk2 * 16.0, _block_sum(g.lmax, g.mmax, g.m_block, 3), [spec]
    if stage == "stokes":
        # the whole channel's Gram over [T, E, B, V] (complex128, full matrices) and its Cholesky factors,
        # one set for the solve, the leakage and the CLEAN of V (PolarisedObserver): two Grams;
        # and the ring FFTs of one pass of at most 64 baselines (polarised_fourier: 16 fields x (+m, -m)
        # per ring and m, complex128, ~lmax / 2 north rings), in m-blocks within FOURIER_BUDGET_BYTES
        gram = 2 * 16.0 * sum((4 * (g.lmax - m + 1)) ** 2 for m in range(g.lmax + 1))
        coef = min(FOURIER_BUDGET_BYTES, 2 * 16 * 2 * 64 * 16.0 * (g.lmax + 1) * (g.lmax // 2 + 2))
        c = cfg.clean  # the CLEAN of V: components and peaks are written for the cycles run
        spec = rs.stokes_store(g.n_split, g.n_freq, g.lmax, g.mmax,
                               (PSF_DECLINATIONS, g.clean_cycles, c.peaks_per_cycle) if c.enabled else None)
        return g.n_freq, gram + coef, g.n_bl * 4 * (g.lmax + 1) ** 2, [spec]
    if stage == "clean":
        c = cfg.clean
        # residuals are written per cycle: the disk holds the cycles run, not max_cycles
        spec = rs.clean_store(g.n_freq, g.lmax, g.mmax, g.m_block, PSF_DECLINATIONS, g.clean_cycles,
                              c.peaks_per_cycle, g.npix, c.keep_factors)
        tasks = g.n_freq * n_mb * (1 + g.clean_cycles)
        return tasks, blk2 * 16.0 * 2, _block_sum(g.lmax, g.mmax, g.m_block, 3), [spec]
    if stage == "products":
        return g.n_freq, g.npix * 8.0 * 8, g.npix + (g.lmax + 1) ** 2, []
    raise KeyError(stage)


def _gram_bytes(lmax, mmax, itemsize):
    """The Gram accumulators of one channel, ``sum_m (lmax - m + 1)^2`` elements (~lmax^3 / 3)."""
    return float(sum((lmax - m + 1) ** 2 for m in range(mmax + 1))) * itemsize


def load_costs(path=COSTS_FILE):
    """The per-stage constants ``{stage: {a, b, c, d}}`` and the ``sgemm_gflops`` they were fitted at."""
    return json.loads(Path(path).read_text())


def estimate(stage, g, cfg, costs, peak_gflops, workers):
    """The :class:`StageEstimate` of one stage on ``workers`` concurrent task slots."""
    tasks, w, u, specs = stage_work(stage, g, cfg)
    k = costs["stages"].get(stage)
    est = StageEstimate(stage, tasks, w, u, int(sum(s.nbytes for s in specs)))
    if k is None:
        est.notes.append("no fitted constants: memory = working set, time unknown")
        est.task_bytes = w
        return est
    if stage == "clean":
        est.notes.append(f"assumes {g.clean_cycles} major cycles: their number depends on the sky")
    est.task_bytes = k["a"] * w + k["b"]
    per_task = (k["c"] * u + k["d"]) * costs["sgemm_gflops"] / peak_gflops
    if stage == "simulate" and g.diffuse_samples:  # the time chunks by the fitted constants, the sums by their flops
        sums = diffuse_sum_seconds(g, peak_gflops)
        est.notes.append(f"the diffuse sky: {g.n_freq * g.diffuse_samples} direct sums, ~{sums / 60:.0f} min")
        est.seconds = per_task * math.ceil(-(-g.n_time // TIME_CHUNK) / max(workers, 1)) + sums
        return est
    est.seconds = per_task * math.ceil(tasks / max(workers, 1))
    return est


#: the share of the SGEMM peak the diffuse sky's direct sums reach (the rank-k product over the antennas and
#: the phasors' sines and cosines), measured 2026-11-27 at full scale: 138 sums of 1.58M points above the
#: horizon at 256 antennas, 889 s of task time on the 2 workers of a 193 GFLOP/s VM
DIFFUSE_SUM_FRACTION = 0.67


def diffuse_sum_seconds(g, peak_gflops):
    """Wall seconds of an interpolated diffuse sky's direct sums on the whole machine: per channel and
    sampled angle ``(2 n_ant)^2 x n_up`` flops (``n_up``, half the quadrature grid, above the horizon), per
    feed column, at :data:`DIFFUSE_SUM_FRACTION` of the SGEMM peak ``peak_gflops``."""
    flops = g.n_freq * g.diffuse_samples * g.n_feed_columns * (2.0 * g.n_ant) ** 2 * g.n_diffuse_points / 2
    return flops / (DIFFUSE_SUM_FRACTION * peak_gflops * 1e9)


def geometry(cfg, ingest=None):
    """The :class:`Geometry` of a configuration: from the telescope for a simulation, from the
    files' metadata (no visibilities read) for ingested data, or from ``ingest`` (an object with the
    ingest plan's ``layout``, ``pairs``, ``n_time``, ``pols`` and ``freqs_hz``: a record's copy,
    :func:`mmflow.workflow.plan.fit.record_ingest`) where the files are not at hand."""
    mm = cfg.mmode
    mmax = mm.mmax if mm.mmax is not None else mm.lmax
    itemsize = 8 if cfg.transfer.dtype == "float32" else 16
    if cfg.source == "simulate":
        tel = build_telescope(cfg)
        o = cfg.observation
        n_time = o.n_integrations or int(round(SIDEREAL_DAY_S / o.integration_s))
        n_pol = 2 if cfg.corrupt.enabled else 1
        freqs = tel.freqs_hz
    else:
        plan = plan_ingest(cfg) if ingest is None else ingest  # a record's copy of the files' plan
        tel = build_telescope(cfg, plan.layout)  # the files' array and baselines, not the config's telescope
        tel.pairs = np.asarray(plan.pairs)
        n_time, n_pol, freqs = plan.n_time, len(plan.pols), np.asarray(plan.freqs_hz)
    n_bl = len(tel.antenna_pairs())
    tplans = [_transfer_plan(tel, float(f), cfg, mmax) for f in freqs]
    nside = cfg.products.nside or default_nside(mm.lmax)
    pts, n_diffuse = _sky_points_count(cfg, tel, freqs) if cfg.source == "simulate" else (0, 0)
    interpolated = cfg.source == "simulate" and interpolates_diffuse(cfg)
    n_feed = len(feed_columns(tel, cfg.corrupt.enabled)) if cfg.source == "simulate" else 1
    cal = cfg.calibrate
    # integrations per solve: an interval, or (solint_s null) the one track where the sources are highest
    interval = int(round((cal.solint_s if cal.solint_s else 60.0 * cal.track_min) / cfg.observation.integration_s))
    return Geometry(n_time=n_time, n_ant=tel.n_ant, n_bl=n_bl, n_freq=len(freqs), n_pol=n_pol, lmax=mm.lmax,
                    mmax=mmax, m_block=cfg.transfer.m_block, n_split=len(mm.splits), mmode_chunk=mm.baseline_chunk,
                    gram_itemsize=itemsize, transfer_units=tuple(p[0] for p in tplans),
                    transfer_workspace=max(p[1] for p in tplans),
                    n_sky_points=pts + (0 if interpolated else n_diffuse), n_diffuse_points=n_diffuse,
                    diffuse_samples=n_samples(cfg.sky.diffuse_lmax) if interpolated else 0, n_feed_columns=n_feed,
                    n_cal_sources=len(cal.sources) if cal.enabled else 0,
                    cal_screen_rounds=cal.screen_rounds if cal.enabled and set(cal.screen_sources) & set(cal.sources)
                    else 0,
                    n_peel_sources=len(cfg.peel.sources) + len(cfg.peel.model_sources) if cfg.peel.enabled else 0,
                    cal_interval=interval, n_models=len(cfg.peel.sources) if cfg.models.enabled else 0,
                    npix=12 * nside ** 2, clean_cycles=min(cfg.clean.max_cycles, EXPECTED_CLEAN_CYCLES) if cfg.clean.enabled else 0)


def _sky_points_count(cfg, tel, freqs):
    """Points the simulator sums: ``(sources, diffuse)``, the diffuse sky's grid as the simulator builds it at
    the highest channel (:func:`mmflow.simulate.scene.diffuse_quad_lmax`,
    :func:`mmflow.simulate.visibilities.gauss_legendre_shape`; 0 without one)."""
    s = cfg.sky
    if not s.diffuse:
        return len(s.sources), 0
    q = diffuse_quad_lmax(tel, float(np.max(freqs)), s.diffuse_lmax, s.quad_oversample)
    ntheta, nphi = gauss_legendre_shape(q)
    return len(s.sources), ntheta * nphi


def plan(cfg, costs=None, peak_gflops=None, ingest=None):
    """Per enabled stage a :class:`StageEstimate`, and the run's totals against its limits.

    Returns
    -------
    dict
        ``stages`` (list of estimates as dicts), ``task_slots`` (tasks running at once, by which each
        stage's per-task time is multiplied), ``total_store_gb``, ``largest_task`` (stage and GB),
        ``worker_memory_gb`` (the cluster's per-worker limit, or None) and ``free_disk_gb`` where
        the run directory will be. ``ingest``: as in :func:`geometry`.
    """
    costs = costs or load_costs()
    if peak_gflops is None:
        peak_gflops = gemm_gflops(np.float32, n=768)
    g = geometry(cfg, ingest)
    workers = cfg.cluster.n_workers * cfg.cluster.threads_per_worker if cfg.cluster.kind != "synchronous" else 1
    ests = [estimate(st.name, g, cfg, costs, peak_gflops, workers) for st in PIPELINE
            if st.enabled(cfg) and st.task is not None]
    largest = max(ests, key=lambda e: e.task_bytes)
    return {"stages": [vars(e) for e in ests], "sgemm_gflops": peak_gflops, "task_slots": workers,
            "total_store_gb": sum(e.store_bytes for e in ests) / 1e9,
            "largest_task": {"stage": largest.stage, "gb": (largest.task_bytes + WORKER_BASE_BYTES) / 1e9},
            "worker_memory_gb": worker_memory_gb(cfg), "free_disk_gb": free_disk_gb(cfg.run.directory),
            "total_seconds": sum(e.seconds for e in ests)}


def worker_memory_gb(cfg):
    """A local worker's memory limit in GB (dask's 'auto' splits the machine among workers);
    None where the cluster is not local (its limit is the scheduler's business)."""
    from dask.utils import parse_bytes  # deferred: dask takes 0.3-0.8 s to import; `mmflow status` loads this

    c = cfg.cluster
    if c.kind not in ("local", "synchronous"):
        return None
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if c.kind == "synchronous" or c.memory_limit == "auto":
        return total / (1 if c.kind == "synchronous" else c.n_workers) / 1e9
    try:
        frac = float(c.memory_limit)
        return frac * total / 1e9
    except ValueError:
        return parse_bytes(c.memory_limit) / 1e9


def free_disk_gb(run_directory):
    """Free bytes (GB) on the file system that holds (or will hold) the run directory."""
    p = Path(expand_path(run_directory)).absolute()
    while not p.exists():
        p = p.parent
    st = os.statvfs(p)
    return st.f_bavail * st.f_frsize / 1e9


def format_plan(res):
    """The plan as a table: per stage tasks, largest task (GB), stores (GB) and time; then totals."""
    rows = [f"{'stage':12s} {'tasks':>7s} {'task GB':>8s} {'store GB':>9s} {'time':>9s}"]
    for e in res["stages"]:
        t = _duration(e["seconds"]) if e["seconds"] else "?"
        rows.append(f"{e['stage']:12s} {e['tasks']:7d} {(e['task_bytes'] + WORKER_BASE_BYTES) / 1e9:8.2f} "
                    f"{e['store_bytes'] / 1e9:9.3f} {t:>9s}" + (f"  ({'; '.join(e['notes'])})" if e["notes"] else ""))
    lt, wm = res["largest_task"], res["worker_memory_gb"]
    rows.append(f"total: {res['total_store_gb']:.3f} GB of stores ({res['free_disk_gb']:.1f} GB free), "
                f"~{_duration(res['total_seconds'])} at {res['sgemm_gflops']:.0f} SGEMM GFLOP/s")
    rows.append(f"largest task: {lt['stage']} {lt['gb']:.2f} GB (with a worker's baseline)"
                + (f" against {wm:.2f} GB per worker" if wm else ""))
    return "\n".join(rows)


def _duration(s):
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min" if s < 7200 else f"{s / 3600:.1f} h"


#: the setting that shrinks each stage's largest task
SHRINK = {"simulate": "fewer channels per run (observation.freqs_mhz)",
          "ingest": "fewer channels per run (observation.freqs_mhz)",
          "calibrate": "a shorter calibrate.solint_s", "peel": "fewer peel.sources / peel.model_sources",
          "models": "fewer models.sources", "terrestrial": "fewer channels per run (observation.freqs_mhz)",
          "mmodes": "a smaller mmode.baseline_chunk", "transfer": "transfer.dtype=float32 (half the Gram)",
          "normal": "a smaller transfer.m_block", "solve": "a smaller transfer.m_block",
          "clean": "a smaller transfer.m_block", "products": "a smaller products.nside"}


def _disk_shrink(stage, cfg):
    """The setting that shrinks a stage's stores on disk (the largest store names it in a refusal)."""
    if stage == "transfer":
        t = cfg.transfer
        return ("transfer.mode=normal (no transfer blocks on disk)" if t.mode != "normal" else
                f"fewer transfer.groups (now {t.groups}: each keeps a partial Gram per channel on disk)")
    if stage == "clean" and cfg.clean.keep_factors:
        return "clean.keep_factors=false (no Cholesky factors on disk)"
    return "fewer channels per run (observation.freqs_mhz)"


def check_fits(cfg, worker_limit_gb, stage_names, free_disk=None, existing_bytes=0):
    """Refuse, before any work, a run whose largest task exceeds a worker's memory or whose stores
    exceed the free disk: an :class:`mmflow.errors.InputError` naming the stage, the estimate, the
    limit and the setting that fixes it. ``existing_bytes``: what the run's stores hold already."""
    g = geometry(cfg)
    costs = load_costs()
    workers = 1
    ests = [estimate(n, g, cfg, costs, costs["sgemm_gflops"], workers) for n in stage_names]
    if worker_limit_gb:
        for e in ests:
            need = (e.task_bytes + WORKER_BASE_BYTES) / 1e9
            if need > worker_limit_gb:
                raise InputError("workflow", f"stage {e.stage}", f"its largest task needs ~{need:.2f} GB "
                                 f"(`mmflow plan`), more than a worker's {worker_limit_gb:.2f} GB memory limit",
                                 f"{SHRINK.get(e.stage, 'a smaller chunk')}, or more memory per worker "
                                 "(fewer cluster.n_workers, a larger cluster.memory_limit)")
    disk = sum(e.store_bytes for e in ests) - existing_bytes
    free = free_disk_gb(cfg.run.directory) if free_disk is None else free_disk
    if disk / 1e9 > free:
        big = max(ests, key=lambda e: e.store_bytes)
        raise InputError(str(cfg.run.directory), "run.directory", f"the stores need up to {disk / 1e9:.2f} GB "
                         f"(`mmflow plan`; {big.stage} {big.store_bytes / 1e9:.2f} GB), more than the "
                         f"{free:.2f} GB free there", f"{_disk_shrink(big.stage, cfg)}, free disk space, or set "
                         "run.directory on a larger file system")
    return ests
