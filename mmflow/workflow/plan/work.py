"""What every stage's cost model shares: the run's :class:`Geometry`, the :class:`Work` a stage returns,
the :class:`Cost` a stage declares, and the sizes of the arrays more than one stage allocates.

Each stage package owns its cost model (``mmflow/workflow/stages/<name>/cost.py``, a :class:`Cost` passed
to its ``Stage``); the planner (:mod:`mmflow.workflow.plan.planner`) iterates the pipeline and never
branches on a stage's name. A cost model counts, from the geometry and the configuration alone:

- ``tasks``: the stage's task count;
- ``working_set_bytes`` ``W``: the largest task's arrays, from the element sizes below;
- ``units`` ``U``: the largest task's work (samples, flops, Gram updates, by the stage's own measure);
- ``stores``: the :class:`mmflow.io.run_stores.StoreSpec` of the stores it writes.

The fitted constants (``costs.json``, :mod:`mmflow.workflow.plan.fit`) turn ``W`` into a task's memory
``a W + b`` and ``U`` into its time ``c U + d``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Optional

import ducc0
import numpy as np

from mmflow.conventions import SPEED_OF_LIGHT, is_full_stokes, m_blocks
from mmflow.io import run_stores as rs
from mmflow.mmode.engine import GridCache, plan_chunks, plan_groups
from mmflow.mmode.normal import packed_size
from mmflow.mmode.transfer import fringe_bandlimit, grid_rings
from mmflow.telescope.beam_factory import JONES_TYPES
from mmflow.workflow.engine.chunking import TIME_CHUNK

#: bytes of one visibility sample as the data stages write it: complex64 visibility + float32 weight
VIS_SAMPLE_BYTES = 8.0 + 4.0
#: bytes of one sample of a corrected block as stages read it: complex128 visibility + float64 weight
CORRECTED_SAMPLE_BYTES = 16.0 + 8.0

def four_correlation_note(ratio):
    """The plan's note on a stage whose task time the four correlations multiply by ``ratio`` (its cost
    model's ``FOUR_CORRELATION_TIME``: the polarised simulation, the sources' E-field models and the cross
    hands' fit, measured against the same tasks with the parallel hands by
    ``benchmarks/four_correlation_ratio.py``, docs/stokes.md)."""
    return f"full Stokes: {ratio:.1f}x the parallel hands' time (the four correlations, docs/stokes.md)"


def four_correlations(cfg):
    """True where peel and terrestrial act on xy and yx too: full Stokes through an E-field beam (the
    configuration's side of :func:`mmflow.workflow.engine.peel_models.four_correlation_jones`)."""
    return is_full_stokes(cfg.imaging.stokes) and cfg.beam.type in JONES_TYPES


#: bytes of a complex128 element (Gram blocks, m-modes, models in double precision)
COMPLEX128_BYTES = 16.0
#: complex (time, baseline, pol) temporaries of the peel's correction on read
#: (:func:`mmflow.workflow.engine.peel_models.peel_components`: the model it builds, each source's term, the
#: gain products and the two ends' gains they come from)
PEEL_TEMPORARIES = 5
#: complex (time, baseline) temporaries per cross hand of the four-correlation correction on read, one source at
#: a time: its templates, their gain products and the cross model it adds (the two ends' gathers go first)
CROSS_TEMPORARIES = 3
#: copies of an array while zarr reads it whole: the chunk's encoded bytes, its decoded buffer and the array
#: returned (solve's Gram blocks: traced 2.9x in the 64-antenna lmax-200 run, whose Grams compress to 0.88 of
#: their size; an array's Grams are dense, 16 core stands' at lmax 1000 mostly zero and 50x smaller encoded;
#: CLEAN's packed factors alike)
ZARR_READ_COPIES = 3
#: copies of an array while zarr writes it: the encoded chunk (traced 1.0x for the m-modes of a baseline chunk,
#: complex128, which do not compress); a region that is part of a chunk is first laid into a chunk-shaped buffer
#: (the last, partial, chunk of a stage's tasks: one copy more, of the full chunk)
ZARR_WRITE_COPIES = 1
#: bytes per source, antenna and pol of the DD gains read and copied
DD_GAIN_BYTES = 2 * COMPLEX128_BYTES
#: declinations of CLEAN's PSF table (the clean stage and the CLEAN of V in the stokes stage)
PSF_DECLINATIONS = 16
#: the setting that shrinks every per-channel task and store
FEWER_CHANNELS = "fewer channels per run (observation.freqs_mhz)"
#: CLEAN's major cycles are data-dependent (until the threshold): the plan assumes this many
EXPECTED_CLEAN_CYCLES = 40


@dataclass(frozen=True)
class Geometry:
    """The sizes of a run every stage's work follows from (integrations, baselines, channels, ...).

    ``tel`` (the telescope with the run's baselines) and ``freqs_hz`` let a stage count what only it
    needs (the simulator's sky points, a calibration's solution intervals); ``transfer_units`` is the
    transfer stage's partition of the Gram work into baseline groups, which the normal stage reduces.
    """

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
    transfer_workspace: float  # bytes of a transfer task besides its Gram while it accumulates (transfer_plan)
    transfer_read: float = 0.0  # bytes of a transfer task's m-modes as it reads them, before its Gram
    npix: int = 0
    n_bins: int = 0  # sidereal bins of the m-mode transform (mmflow.workflow.engine.geometry.n_bins_of)
    task_threads: int = 1  # threads each task's kernels run on (planner.task_threads: the workers' n_threads)
    tel: object = field(default=None, compare=False, repr=False)
    freqs_hz: tuple = ()

    @property
    def n_groups(self):
        """Baseline groups of the transfer stage (partial normal equations per channel)."""
        return max(len(u) for u in self.transfer_units)

    @property
    def gram_dtype(self):
        return "complex64" if self.gram_itemsize == 8 else "complex128"

    @property
    def n_time_chunks(self):
        """Time chunks of :data:`TIME_CHUNK` integrations (:mod:`mmflow.workflow.engine.chunking`)."""
        return -(-self.n_time // TIME_CHUNK)

    @property
    def chunk_integrations(self):
        """Integrations of the largest time chunk."""
        return min(TIME_CHUNK, self.n_time)

    @property
    def vis_task_bytes(self):
        """One time chunk of every channel's visibilities and weights as written (``vis.zarr``)."""
        return self.chunk_integrations * self.n_bl * self.n_freq * self.n_pol * VIS_SAMPLE_BYTES


class Work(NamedTuple):
    """A stage's work from the geometry: ``(tasks, working_set_bytes, units, stores)``."""

    tasks: int
    working_set_bytes: float
    units: float
    stores: list


@dataclass(frozen=True)
class Cost:
    """A stage's cost model.

    Parameters
    ----------
    work : callable
        ``work(g, cfg) -> Work``.
    shrink : str or callable
        The setting that shrinks the stage's largest task (``shrink(cfg) -> str`` where it depends on
        the configuration), named when the task does not fit a worker.
    disk_shrink : str or callable
        The setting that shrinks the stage's stores on disk, named when they do not fit the disk.
    seconds : callable, optional
        ``seconds(g, cfg, per_task, workers, peak_gflops) -> seconds``, for a stage whose wall time is
        not ``per_task`` times its rounds of tasks (the simulator's diffuse sums).
    notes : callable, optional
        ``notes(g, cfg, peak_gflops) -> [str]``: what the plan assumes for this stage.
    split : callable, optional
        ``split(cfg) -> [{dotted.setting: value, ...}, ...]``: settings that shrink the largest task
        without changing the science, each smaller than the one before (e.g. :func:`halvings`); the
        cluster plan (:mod:`mmflow.workflow.plan.jobs`) re-plans with them, in order, until the task
        fits a node. None: the task cannot be split (:attr:`shrink` names what to change instead).
    """

    work: Callable
    shrink: object = FEWER_CHANNELS
    disk_shrink: object = FEWER_CHANNELS
    seconds: Optional[Callable] = None
    notes: Optional[Callable] = None
    split: Optional[Callable] = None

    def split_settings(self, cfg):
        """The :attr:`split` candidates under ``cfg`` (``[]`` where the task cannot be split)."""
        return list(self.split(cfg)) if self.split is not None else []

    def shrink_setting(self, cfg):
        return self.shrink(cfg) if callable(self.shrink) else self.shrink

    def disk_shrink_setting(self, cfg):
        return self.disk_shrink(cfg) if callable(self.disk_shrink) else self.disk_shrink


def setting(cfg, key):
    """The value of a dotted setting (``"transfer.baseline_chunk"``) of a configuration."""
    value = cfg
    for part in key.split("."):
        value = getattr(value, part)
    return value


def halvings(key, floor=1):
    """A :attr:`Cost.split`: ``key`` halved, then quartered, ... down to ``floor`` (integers)."""
    def split(cfg):
        v, out = int(setting(cfg, key)), []
        while v // 2 >= floor:
            v //= 2
            out.append({key: v})
        return out
    return split


def read_bytes(g, cfg, n_time, n_bl, n_freq):
    """Bytes of a block of ``n_time x n_bl x n_freq`` as :func:`mmflow.workflow.engine.blocks.read_block`
    returns it to a stage after the peel (complex128 + float64 a sample; with the four correlations its cross
    hands too, ``n_cross = 2``) and, with peeling on, the peel's correction of one channel on read
    (:func:`mmflow.workflow.engine.peel_models.peel_components`): per integration and baseline the sources'
    models (the parallel hands: every source's, ``n_models = n_sub``; four correlations: one source's four at a
    time, ``n_models = 4``), the :data:`PEEL_TEMPORARIES` complex arrays per pol of the parallel hands and the
    :data:`CROSS_TEMPORARIES` per cross hand of a source's cross hands, per integration every source's DD gains
    read and copied::

        n_time (n_bl n_freq (n_pol + n_cross) 24 + n_bl 16 (n_models + 5 n_pol + 3 n_cross) + 32 n_sub n_ant n_pol)

    (measured 0.75 GB at 6,628 integrations and 64 antennas, 1.22 GB at 256; 1.34 GB traced for a time
    chunk of the 352-antenna array, one pol and four sources, against 1.34 counted: docs/planning.md; four
    correlations: 3.71 GB in a terrestrial task of the paper's array against 3.87 planned, docs/stokes.md)."""
    n_sub = len(cfg.peel.sources) if cfg.peel.enabled else 0
    four = four_correlations(cfg)
    n_cross, n_models = (2, 4) if four else (0, n_sub)
    total = block_bytes(g, n_time, n_bl, n_freq, four)
    if n_sub:
        total += n_time * (n_bl * COMPLEX128_BYTES * (n_models + PEEL_TEMPORARIES * g.n_pol
                                                      + CROSS_TEMPORARIES * n_cross)
                           + DD_GAIN_BYTES * n_sub * g.n_ant * g.n_pol)
    return total


def block_bytes(g, n_time, n_bl, n_freq, cross):
    """Bytes of a corrected block as :func:`mmflow.workflow.engine.blocks.read_block` returns it, once read:
    ``n_time n_bl n_freq (n_pol + n_cross) 24`` (complex128 + float64 a sample; ``n_cross = 2`` where
    ``cross``, the four correlations' xy and yx)."""
    return n_time * n_bl * n_freq * (g.n_pol + (2 if cross else 0)) * CORRECTED_SAMPLE_BYTES


def vis_spec(g):
    """The ``vis.zarr`` the data stages write, sized by the geometry."""
    return rs.vis_store(g.n_time, np.zeros((g.n_bl, 2), int), np.zeros(g.n_freq), np.zeros((g.n_ant, 3)),
                        {"pols": ["p"] * g.n_pol}, TIME_CHUNK, g.mmode_chunk)


def expected_clean_cycles(cfg):
    """The major cycles the plan assumes for CLEAN (0 when it is off)."""
    return min(cfg.clean.max_cycles, EXPECTED_CLEAN_CYCLES) if cfg.clean.enabled else 0


def gram_bytes(lmax, mmax, itemsize):
    """The Gram accumulators of one channel, ``sum_m (lmax - m + 1)^2`` elements (~lmax^3 / 3)."""
    return float(sum((lmax - m + 1) ** 2 for m in range(mmax + 1))) * itemsize


def gram_work(lmax_c, mmax):
    """``sum_{m <= min(mmax, lmax_c)} (lmax_c - m + 1)^2``: one baseline's Gram updates."""
    n = np.arange(lmax_c - min(mmax, lmax_c) + 1, lmax_c + 2, dtype=float)
    return float(np.sum(n * n))


def block_sum(lmax, mmax, m_block, power):
    """Largest ``sum_{m in block} (lmax - m + 1)^power`` over the m blocks (the first block)."""
    return max(float(sum((lmax - m + 1) ** power for m in range(m0, m1))) for m0, m1 in m_blocks(mmax, m_block))


def packed_block_sum(lmax, mmax, m_block):
    """Largest ``(m1 - m0) n0 (n0 + 1) / 2``, ``n0 = lmax - m0 + 1``, over the m blocks: the elements of a block's
    Grams as the stores hold them (each m's padded upper triangle, packed: :func:`mmflow.mmode.normal.pack_upper`)."""
    return max(float((m1 - m0) * packed_size(lmax - m0 + 1)) for m0, m1 in m_blocks(mmax, m_block))


def n_m_blocks(g):
    """The m blocks of the per-m stages."""
    return len(m_blocks(g.mmax, g.m_block))


#: bytes of an m-mode as ``mmodes.zarr`` holds it and the transfer task reads it (complex128)
MMODE_BYTES = 16.0
#: bytes of a transfer grid's point: its direction (3 float64) and the beam on it (float64)
#: (:class:`mmflow.mmode.transfer.TransferGrid`'s ``vectors`` and ``beam``)
GRID_POINT_BYTES = 4 * 8.0
#: the time of one fringe sample of the transfer's Fourier stage (a baseline's fringe on a north ring's
#: point and its mirror's, folded, and its share of the rings' FFTs) in Gram updates: measured on this VM
#: (one thread, float32) 58 ns a sample on the 352-antenna array's longest baselines against 1.25 ns a Gram
#: update at lmax 300-500 (the least-squares split of four chunks' times into the two; docs/planning.md)
FRINGE_SAMPLE_UNITS = 46.0


def transfer_plan(tel, freq_hz, cfg, mmax):
    """Per baseline group of one channel (the transfer stage's own :func:`plan_chunks` and
    :func:`plan_groups`) its Gram work ``sum_chunks n_c sum_{m <= lmax_c} (lmax_c - m + 1)^2``, and the
    bytes of a task besides its Gram, ``(read, workspace)``, each the largest over the groups:

    - ``read``: the channel's m-modes as the task reads them (every baseline, ``n_split x (mmax + 1)
      x 2`` complex128 each) and the group's columns copied out of them, before the Gram exists;
    - ``workspace``, while it accumulates: the group's m-modes and, of its largest chunk (chunks of
      short baselines hold up to :data:`mmflow.mmode.engine.MAX_CHUNK_FACTOR` x
      ``transfer.baseline_chunk`` baselines), on the chunk's own grid (:class:`mmflow.mmode.engine.GridCache`'s
      buckets: ``l_g``, exact to ``l_g +`` its fringe band limit, ``n_theta`` rings of ``n_phi`` points,
      :func:`mmflow.mmode.transfer.make_grid`; one grid held at a time) the grid's directions and beam
      (:data:`GRID_POINT_BYTES` a point), the float tables ``n_theta / 2 x (l_g + 1)(l_g + 2) / 2``, the
      ring-Fourier buffers ``2 x (m_top + 1) x n_theta / 2 x 2 n_chunk`` complex, the chunk's m-modes
      (complex128) and their weighted copy (:func:`mmflow.mmode.engine.add_chunk`, in the Gram's
      precision) and the row mask ``(lmax + 1) x 2 n_chunk`` real. The grid's points grow with the
      fringe band limit, not with lmax: at lmax 50 the 352-antenna array's longest baselines (fringe
      band limit ~3,950) take grids of ~7M points, 0.22 GB, beside 0.6 GB of buffers.

    The units of a group: its Gram work plus :data:`FRINGE_SAMPLE_UNITS` per fringe sample of its
    chunks' Fourier stage, ``sum_chunks n_c x n_active x n_phi`` (:func:`mmflow.mmode.transfer.fourier_stage`:
    every baseline's beam-weighted fringe on every point of its chunk's grid, then the rings' FFTs). Where
    ``lmax`` is near the baselines' own band limits the Gram work dominates (``~ n lmax^3 / 3`` against
    ``~ n lmax^2``); at a low ``lmax`` with long baselines the Fourier stage does (the 352-antenna array at
    lmax 50: 96 % of the transfer's time)."""
    t = cfg.transfer
    lmax = cfg.mmode.lmax
    n_split = len(cfg.mmode.splits)
    chunks, lmax_b = plan_chunks(tel, freq_hz, lmax, t.baseline_chunk, t.per_baseline_lmax)
    real = 4 if t.dtype == "float32" else 8
    cplx = 2 * real
    hint = tel.beam.lmax_hint
    lengths = np.linalg.norm(tel.baselines_enu(), axis=1) * freq_hz / SPEED_OF_LIGHT

    def grid_of(c):
        glmax, fringe = GridCache.key(c.lmax, fringe_bandlimit(lengths[c.index], hint), lmax)
        rings = grid_rings(glmax, fringe)
        return glmax, rings, grid_points(glmax, fringe)

    def chunk_bytes(c):
        glmax, rings, points = grid_of(c)
        half_rings = rings / 2
        m_top, nb = min(mmax, c.lmax), len(c.index)
        tables = half_rings * (glmax + 1) * (glmax + 2) / 2 * real
        fourier = 2 * (m_top + 1) * half_rings * 2 * nb * cplx
        data = n_split * (m_top + 1) * 2 * nb * (MMODE_BYTES + cplx)
        return points * GRID_POINT_BYTES + tables + fourier + data + (lmax + 1) * 2 * nb * real

    def fringe_samples(c):  # the north rings (each folded with its mirror) x their points, per baseline
        return len(c.index) * grid_of(c)[2] / 2

    mode_bytes = n_split * (mmax + 1) * 2 * MMODE_BYTES  # one baseline's m-modes
    units, read, work = [], 0.0, 0.0
    for group in plan_groups(chunks, t.groups):
        units.append(sum(len(c.index) * gram_work(c.lmax, mmax) + FRINGE_SAMPLE_UNITS * fringe_samples(c)
                         for c in group))
        n = sum(len(c.index) for c in group)
        read = max(read, mode_bytes * (len(lmax_b) + n))
        work = max(work, mode_bytes * n + max(chunk_bytes(c) for c in group))
    return tuple(units), read, work


def grid_points(glmax, fringe_lmax):
    """Points of the transfer grid exact to ``glmax + fringe_lmax``: ``n_theta x n_phi``
    (:func:`mmflow.mmode.transfer.make_grid`)."""
    return grid_rings(glmax, fringe_lmax) * ducc0.fft.good_size(glmax + fringe_lmax + 2)
