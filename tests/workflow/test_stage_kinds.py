"""The runner's stage kinds with toy stages: solve-then-apply (corrections on read) and iterative.

The real calibration and CLEAN stages plug into the same mechanics; these tests pin the
mechanics down: a correction solved on intervals that cross storage chunks is applied exactly
once where the data are read and never written back, and an iterative loop checkpoints each
cycle and resumes bit-identically after a kill.
"""
import numpy as np
import pytest
import zarr

from mmflow.io.run_stores import ArrayName
from mmflow.io.stores import ArraySpec, StoreSpec
from mmflow.workflow.engine.runner import run_workflow
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.stages.base import Stage
from mmflow.workflow.engine.task_key import TaskKey
from tests.workflow_helpers import small_config

QUIET = dict(progress=False, log=lambda *a: None)
INTERVAL = 5  # integrations per solution interval: intervals cross the 256-row storage chunks


def _gain(k):
    return 1.0 + 0.05 * np.sin(k)  # the toy "solution" of interval k (any deterministic solve would do)


def _cal_prepare(ctx):
    n_time = ctx.open("vis.zarr")["lst"].shape[0]
    n_int = -(-n_time // INTERVAL)
    ctx.create(StoreSpec("gains.zarr", (ArraySpec("gain", ("interval",), (n_int,), (1,), "float64"),)))
    return [TaskKey(phase="g", freq=0, interval=k) for k in range(n_int)]


def _cal_task(ctx, key):
    k = key.interval
    rows = slice(k * INTERVAL, (k + 1) * INTERVAL)
    vis = ctx.read(ArrayName("vis.zarr", "vis"), (rows,))  # reads the chunks the interval touches, verified
    assert vis.shape[0] >= 1
    ctx.write(ctx.open("gains.zarr", mode="r+"), "gain", (slice(k, k + 1),), np.array([_gain(k)]))


def _cal_apply(ctx, block):
    gain = ctx.read(ArrayName("gains.zarr", "gain"))
    per_row = np.repeat(gain, INTERVAL)[block.rows]
    block.vis /= per_row[:, None, None, None]


def _toy_calibrate():
    return Stage("calibrate", ("calibrate",), ("vis.zarr",), ("gains.zarr",), _cal_prepare, _cal_task,
                 enabled=lambda cfg: cfg.calibrate.enabled, kind="solve", apply=_cal_apply,
                 description="toy: per-interval scalar gains")


@pytest.fixture
def toy_stages():
    """The run's keywords with mmflow's pipeline, its calibrate and clean stages replaced by toys."""
    return dict(QUIET, pipeline=PIPELINE.replace(_toy_calibrate(), _toy_clean()))


def test_correction_is_applied_once_on_read_and_never_written_back(toy_stages, tmp_path):
    plain, cal = tmp_path / "plain", tmp_path / "cal"
    run_workflow(small_config(plain, "run.keep=[vis.zarr]"), only=["simulate", "mmodes"], **toy_stages)
    run_workflow(small_config(cal, "calibrate.enabled=true", "run.keep=[vis.zarr]"),
                 only=["simulate", "calibrate", "mmodes"], **toy_stages)
    v_plain = zarr.open_group(str(plain / "vis.zarr"))["vis"][:]
    assert np.array_equal(v_plain, zarr.open_group(str(cal / "vis.zarr"))["vis"][:])  # vis.zarr untouched
    # the corrected m-modes are the m-modes of vis / gain: check one baseline against a direct transform
    from mmflow.mmode.transform import sidereal_bins, split_mmode_transform

    g = zarr.open_group(str(cal / "vis.zarr"))
    lst = g["lst"][:]
    n = len(lst)
    gain = np.repeat([_gain(k) for k in range(-(-n // INTERVAL))], INTERVAL)[:n]
    mg = zarr.open_group(str(cal / "mmodes.zarr"))
    binned, _, off = sidereal_bins(lst, v_plain[:, 5, 0, 0].astype(complex) / gain, None, mg.attrs["n_bins"], 0.9)
    expect = split_mmode_transform(binned, mg.attrs["mmax"], off)[0]
    np.testing.assert_allclose(mg["mmodes"][0, 0, :, :, 5], expect, rtol=1e-12, atol=1e-12 * np.abs(expect).max())
    # recomputing the m-modes (another setting) reads and corrects again: still applied once
    run_workflow(small_config(cal, "calibrate.enabled=true", "mmode.min_coverage=0.9"), only=["mmodes"],
                 force=True, **toy_stages)
    np.testing.assert_allclose(zarr.open_group(str(cal / "mmodes.zarr"))["mmodes"][0, 0, :, :, 5], expect,
                               rtol=1e-12, atol=1e-12 * np.abs(expect).max())


class Crash(BaseException):
    pass


def test_killed_solve_stage_resumes_bit_identical(toy_stages, tmp_path):
    ref, run = tmp_path / "ref", tmp_path / "run"
    run_workflow(small_config(ref, "calibrate.enabled=true"), only=["simulate", "calibrate", "mmodes"], **toy_stages)
    calls = {"n": 0}

    def dying(ctx, key):
        calls["n"] += 1
        if calls["n"] == 7:
            raise Crash()
        return _cal_task(ctx, key)

    toy = toy_stages["pipeline"]
    dying_pipeline = toy.replace(Stage(**{**vars(toy.stage("calibrate")), "task": dying}))
    with pytest.raises(Crash):
        run_workflow(small_config(run, "calibrate.enabled=true"), only=["simulate", "calibrate", "mmodes"],
                     **dict(toy_stages, pipeline=dying_pipeline))
    run_workflow(small_config(run, "calibrate.enabled=true"), only=["simulate", "calibrate", "mmodes"], **toy_stages)
    for store, arr in (("gains.zarr", "gain"), ("mmodes.zarr", "mmodes")):
        assert np.array_equal(zarr.open_group(str(ref / store))[arr][:], zarr.open_group(str(run / store))[arr][:])


# ----------------------------------------------------------------------------- iterative

N_BLOCKS, MAX_CYCLES, THRESHOLD = 4, 20, 1e-3


def _clean_prepare(ctx):
    ctx.create(StoreSpec("clean.zarr", (
        ArraySpec("level", ("cycle", "block"), (MAX_CYCLES + 1, N_BLOCKS), (1, 1), "float64"),)))
    return []


def _clean_next(ctx, cycle):
    g = ctx.open("clean.zarr", mode="r+")
    if cycle == 0:  # the starting state, from the solve's alm
        alm = ctx.read(ArrayName("alm.zarr", "alm"))[0, 0]
        for b, part in enumerate(np.array_split(np.abs(alm), N_BLOCKS)):
            ctx.write(g, "level", (slice(0, 1), slice(b, b + 1)), np.array([[part.sum()]]))
    level = g["level"][cycle]
    if level.max() < THRESHOLD * g["level"][0].max() or cycle == MAX_CYCLES:
        return None
    return [TaskKey(freq=0, m_block=b) for b in range(N_BLOCKS) if level[b] > 0]


def _clean_task(ctx, key):
    c, b = key.cycle, key.m_block
    g = ctx.open("clean.zarr", mode="r+")
    ctx.write(g, "level", (slice(c + 1, c + 2), slice(b, b + 1)), g["level"][c:c + 1, b:b + 1] * (0.35 + 0.1 * b))


def _toy_clean():
    return Stage("clean", ("clean",), ("alm.zarr",), ("clean.zarr",), _clean_prepare, _clean_task,
                 enabled=lambda cfg: cfg.clean.enabled, kind="iterative", next_cycle=_clean_next,
                 description="toy: a geometric loop to a threshold")


UP_TO_CLEAN = ["simulate", "mmodes", "transfer", "normal", "solve", "clean"]  # products would want the real CLEAN


def test_iterative_stage_checkpoints_each_cycle_and_resumes_bit_identical(toy_stages, tmp_path, monkeypatch):
    from mmflow.workflow.engine.rundir import RunDir

    ref, run = tmp_path / "ref", tmp_path / "run"
    run_workflow(small_config(ref, "clean.enabled=true", "clean.rel_threshold=0.5", "clean.min_separation_deg=10"),
                     only=UP_TO_CLEAN, **toy_stages)
    level = zarr.open_group(str(ref / "clean.zarr"))["level"][:]
    n_cycles = sum(1 for k in RunDir(ref).manifest("clean")["keys"] if k.startswith("cycle"))
    assert 3 <= n_cycles < MAX_CYCLES and level[n_cycles].max() < THRESHOLD * level[0].max()
    real = RunDir.mark_done

    def die_at_cycle_3(self, stage, key, info, chunks):
        real(self, stage, key, info, chunks)
        if key == "cycle0002":
            raise Crash()

    monkeypatch.setattr(RunDir, "mark_done", die_at_cycle_3)
    with pytest.raises(Crash):
        run_workflow(small_config(run, "clean.enabled=true", "clean.rel_threshold=0.5", "clean.min_separation_deg=10"),
                     only=UP_TO_CLEAN, **toy_stages)
    monkeypatch.setattr(RunDir, "mark_done", real)
    s = run_workflow(small_config(run, "clean.enabled=true", "clean.rel_threshold=0.5", "clean.min_separation_deg=10"),
                     only=UP_TO_CLEAN, **toy_stages)
    assert s["clean"]["tasks_run"] == sum(1 for k in RunDir(run).manifest("clean")["keys"]
                                          if k.startswith("c0") and int(k[1:5]) >= 3)
    assert np.array_equal(level, zarr.open_group(str(run / "clean.zarr"))["level"][:])
