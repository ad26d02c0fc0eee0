"""Fault injection: every fault ends bit-identical to an uninterrupted run, or stops naming file and fix.

Kills of the driver at every stage boundary and inside ``prepare`` (crashes injected in
process; real SIGKILLs in tests/workflow/test_workflow.py), a resume on another cluster size, two
runs in one directory, deleted / truncated / altered chunks, changed input files, files a
user put among the outputs, and stages without workers.
"""
import os
import shutil
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest

from mmflow.errors import MmflowError, StaleOutputError
from mmflow.io.stores import DamagedStoreError
from mmflow.workflow.engine.context import Context
from mmflow.workflow.engine.rundir import RunDir, RunLockedError
from mmflow.workflow.engine.runner import run_task, run_workflow, stage_fingerprints, verify
from mmflow.workflow.pipeline import PIPELINE
from tests.workflow_helpers import SMALL, assert_identical, read_outputs, small_config
from tests.workflow_helpers import ROOT, interrupt_run

QUIET = dict(progress=False, log=lambda *a: None)


@pytest.fixture(scope="module")
def ref(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("fref") / "run"
    run_workflow(small_config(run_dir), **QUIET)
    return run_dir, read_outputs(run_dir)


def _copy(ref, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(ref[0], dst)
    return dst


def _chunk(run_dir, stage, store):
    """One chunk file a stage recorded in its markers (first in sorted order)."""
    return sorted(p for p in RunDir(run_dir).chunk_index(stage) if p.startswith(store))[0]


# ----------------------------------------------------------------------------- kills and resumes

class Crash(BaseException):
    """Stands for a kill: nothing after it runs (the lock goes with the process, as with SIGKILL)."""


STAGES = ["simulate", "mmodes", "transfer", "normal", "solve", "products"]


@pytest.mark.parametrize("stage", STAGES)
def test_kill_at_each_stage_boundary_and_inside_prepare_resumes_bit_identical(ref, tmp_path, stage, monkeypatch):
    from mmflow.io import stores

    run_dir = tmp_path / "run"
    real_finish = RunDir.finish_stage

    def finish_then_die(self, name, summary):
        real_finish(self, name, summary)
        if name == stage:
            raise Crash()

    monkeypatch.setattr(RunDir, "finish_stage", finish_then_die)
    with pytest.raises(Crash):
        run_workflow(small_config(run_dir), **QUIET)
    monkeypatch.undo()
    # now die half-way through the next stage's prepare (after some arrays were created)
    calls = {"n": 0}

    def create_then_die(self, root):
        import zarr

        g = zarr.open_group(str(os.path.join(root, self.path)), mode="a")
        for spec in self.arrays[: max(1, len(self.arrays) // 2)]:
            if spec.name not in g and spec.data is None:
                g.create_array(spec.name, shape=spec.shape, chunks=spec.chunks, dtype=spec.dtype)
        calls["n"] += 1
        raise Crash()

    # after solve: products creates no store, and the stages before it, finished, read arrays released
    # since (vis.zarr's visibilities, the m-modes): none prepares again
    if stage not in ("solve", "products"):
        monkeypatch.setattr(stores.StoreSpec, "create", create_then_die)
        with pytest.raises(Crash):
            run_workflow(small_config(run_dir), **QUIET)
        monkeypatch.undo()
        assert calls["n"] == 1
    run_workflow(small_config(run_dir), **QUIET)
    assert_identical(ref[1], read_outputs(run_dir))


def test_half_written_array_metadata_from_a_kill_is_rebuilt(ref, tmp_path):
    run_dir = tmp_path / "run"
    with pytest.raises(MmflowError):
        run_workflow(small_config(run_dir), only=["solve"], **QUIET)  # nothing upstream yet: refused
    run_workflow(small_config(run_dir), **QUIET)
    shutil.rmtree(run_dir / "alm.zarr")
    shutil.rmtree(run_dir / "_status" / "solve")
    shutil.rmtree(run_dir / "_status" / "products")
    run_workflow(small_config(run_dir), only=["simulate"], **QUIET)
    (run_dir / "alm.zarr" / "eps_grid").mkdir(parents=True)
    (run_dir / "alm.zarr" / "eps_grid" / "zarr.json").write_text('{"shape": [20')  # torn write
    run_workflow(small_config(run_dir), **QUIET)
    assert_identical(ref[1], read_outputs(run_dir))


def test_resume_on_another_cluster_size_is_bit_identical(tmp_path):
    """SIGKILL the driver inside transfer on 1 local worker; resume on 2 workers. The reference ran
    uninterrupted on 3 workers: on one executor kind (worker processes), bits never depend on the cluster.
    (Killed on one worker: transfer's two tasks then run one after the other, so the kill lands between
    them; on two workers they finish together and the stage can be complete before the signal.)"""
    from mmflow.cli import main

    # products.png=false: the maps compared are the FITS files; a PNG costs each run ~2 s in a worker
    local = ["cluster.kind=local", "cluster.dashboard_address=:0", "products.png=false"]

    def cli(run_dir, *extra):
        return main(["run", "workflows/demo.yaml", *SMALL, *local, *extra, f"run.directory={run_dir}",
                     "--no-progress"])

    assert cli(tmp_path / "ref", "cluster.n_workers=3") == 0
    run_dir = tmp_path / "run"
    interrupt_run(run_dir, "transfer", signal.SIGKILL, extra=local + ["cluster.n_workers=1"])
    assert cli(run_dir, "cluster.n_workers=2") == 0
    assert_identical(read_outputs(tmp_path / "ref"), read_outputs(run_dir))


def test_work_decomposition_never_reads_cluster_settings():
    for st in PIPELINE:
        assert not any(c == "cluster" or c.startswith("cluster.") for c in st.config), st.name


def test_finish_refuses_a_stage_with_a_key_not_done(ref, tmp_path):
    run_dir = _copy(ref, tmp_path)
    run = RunDir(run_dir)
    key = run.manifest("normal")["keys"][0]
    run.marker("normal", key).unlink()
    with pytest.raises(MmflowError, match=f"1 of .* chunks have no completion marker \\(first: {key}\\)"):
        run.finish_stage("normal", {})


# ----------------------------------------------------------------------------- concurrency

def test_second_run_in_a_directory_is_refused_naming_the_holder(tmp_path):
    run = RunDir(tmp_path / "run")
    fh, _ = run.acquire_lock()
    try:
        with pytest.raises(RunLockedError, match=f"host {socket.gethostname()}, pid {os.getpid()}"):
            run_workflow(small_config(tmp_path / "run", "imaging.eps=0.1"), **QUIET)
    finally:
        fh.close()
    assert not (tmp_path / "run" / "vis.zarr").exists()  # refused before any work


def test_lock_of_a_killed_driver_does_not_block(tmp_path):
    """A driver killed while holding the lock leaves its name in the lock file but no lock: the next
    run takes the directory over (and then holds it against a third)."""
    import json
    import signal

    code = ("import os; from mmflow.workflow.engine.rundir import RunDir; "
            f"RunDir({str(tmp_path / 'run')!r}).acquire_lock(); os.kill(os.getpid(), 9)")
    child = subprocess.run([sys.executable, "-c", code], cwd=ROOT)
    assert child.returncode == -signal.SIGKILL  # killed while holding it
    run = RunDir(tmp_path / "run")
    dead = json.loads(run.lock_path.read_text())
    assert dead["pid"] != os.getpid()  # the dead child wrote it
    fh, token = run.acquire_lock()
    try:
        now = json.loads(run.lock_path.read_text())
        assert (now["pid"], now["token"]) == (os.getpid(), token) and token != dead["token"]
        third = subprocess.run([sys.executable, "-c", "from mmflow.workflow.engine.rundir import RunDir; "
                                f"RunDir({str(tmp_path / 'run')!r}).acquire_lock()"], cwd=ROOT,
                               capture_output=True, text=True)
        assert third.returncode != 0 and f"pid {os.getpid()}" in third.stderr
    finally:
        fh.close()


def test_task_of_a_superseded_driver_stops_before_writing(ref, tmp_path):
    run_dir = _copy(ref, tmp_path)
    fh, _ = RunDir(run_dir).acquire_lock()
    try:
        with pytest.raises(MmflowError, match="now held by another mmflow run"):
            run_task(Context(small_config(run_dir).model_dump_json(), str(run_dir), "old-token"), PIPELINE, "products",
                     "f0")
    finally:
        fh.close()


def test_worker_that_cannot_see_the_run_directory_fails_with_the_fix(tmp_path):
    ctx = Context(small_config(tmp_path / "elsewhere").model_dump_json(), str(tmp_path / "elsewhere"), "t")
    with pytest.raises(MmflowError, match="not visible on host .* filesystem that the driver and every worker"):
        run_task(ctx, PIPELINE, "products", "f0")


def test_relative_run_directory_is_made_absolute_by_the_driver(tmp_path, monkeypatch):
    from mmflow.workflow.config.schema import load_config

    monkeypatch.chdir(tmp_path)
    cfg = load_config(os.path.join(ROOT, "workflows", "demo.yaml"), SMALL + ["run.directory=rel/run"])
    assert RunDir(cfg.run.directory).path == tmp_path / "rel" / "run"


def test_a_stage_without_workers_fails_naming_the_stage(tmp_path):
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as cluster, Client(cluster) as client:
        with pytest.raises(MmflowError, match="stage 'simulate': no dask worker for 1 s"):
            run_workflow(small_config(tmp_path / "run", "cluster.worker_wait_s=1"), client=client, **QUIET)


# ----------------------------------------------------------------------------- damage

def test_deleted_chunk_is_named_and_force_recomputes_only_it(ref, tmp_path):
    run_dir = _copy(ref, tmp_path)
    rel = _chunk(run_dir, "simulate", "vis.zarr/lst")
    (run_dir / rel).unlink()
    problems = verify(run_dir)
    assert problems["simulate"] == [f"{run_dir / rel}: missing"] and problems["mmodes"] == []
    with pytest.raises(DamagedStoreError, match=f"{rel}: missing.*--force"):
        run_workflow(small_config(run_dir), **QUIET)
    s = run_workflow(small_config(run_dir), force=True, **QUIET)
    # the time chunk wrote visibilities released since (after mmodes): simulate is made again whole, bit
    # for bit (the diffuse sky's samples too), and nothing after it
    assert s["simulate"]["tasks_run"] == s["simulate"]["tasks"] and s["mmodes"]["tasks_run"] == 0
    assert not (run_dir / "diffuse.zarr").exists() and RunDir(run_dir).released("simulate")
    assert_identical(ref[1], read_outputs(run_dir))
    assert not any(verify(run_dir).values())


def test_truncated_chunk_is_named(ref, tmp_path):
    run_dir = _copy(ref, tmp_path)
    rel = _chunk(run_dir, "mmodes", "mmodes.zarr/inv_var")  # the m-modes: released after transfer
    data = (run_dir / rel).read_bytes()
    (run_dir / rel).write_bytes(data[: len(data) // 2])
    with pytest.raises(DamagedStoreError, match=f"{rel}: {len(data) // 2} bytes, {len(data)} were written"):
        run_workflow(small_config(run_dir), only=["transfer"], **QUIET)
    assert verify(run_dir)["mmodes"]


def test_altered_chunk_is_refused_when_read(ref, tmp_path):
    """Same size, other bytes: only the checksum finds it; the stage reading it names the file."""
    run_dir = _copy(ref, tmp_path)
    rel = _chunk(run_dir, "normal", "normal.zarr/f0/gram_b")
    data = bytearray((run_dir / rel).read_bytes())
    data[len(data) // 2] ^= 0xFF
    (run_dir / rel).write_bytes(bytes(data))
    assert verify(run_dir, full=False)["normal"] == []  # sizes are fine
    assert "contents changed" in verify(run_dir)["normal"][0]
    with pytest.raises(DamagedStoreError, match=f"{rel}: contents changed"):
        run_workflow(small_config(run_dir, "imaging.eps=0.05"), force=True, **QUIET)


def test_nan_about_to_be_written_is_refused_naming_stage_array_and_chunk(ref, tmp_path, monkeypatch):
    from mmflow.imaging import solvers

    run_dir = _copy(ref, tmp_path)
    real = solvers.solve_block
    monkeypatch.setattr(solvers, "solve_block", lambda *a, **k: real(*a, **k) * np.nan)
    with pytest.raises(MmflowError, match=r"stage 'solve' was about to write \d+ NaN/inf values to .*alm.zarr/alm"):
        run_workflow(small_config(run_dir, "imaging.eps=0.05"), force=True, **QUIET)


# ----------------------------------------------------------------------------- what --force may remove

def test_force_removes_only_files_mmflow_listed(ref, tmp_path):
    run_dir = _copy(ref, tmp_path)
    mine = run_dir / "maps" / "my_notes.txt"
    mine.write_text("a user's file")
    with pytest.raises(StaleOutputError, match=r"products.png: True -> False"):
        run_workflow(small_config(run_dir, "products.png=false"), **QUIET)
    run_workflow(small_config(run_dir, "products.png=false"), force=True, **QUIET)
    assert mine.read_text() == "a user's file"
    assert not list((run_dir / "maps").glob("*.png"))  # mmflow's own PNGs went with the stale stage


def test_product_names_are_unique_for_close_frequencies():
    from mmflow.workflow.stages.products.stage import frequency_tags

    assert frequency_tags([40.0001e6, 40.0002e6]) == ["40.0001MHz", "40.0002MHz"]
    assert frequency_tags([40e6, 50e6]) == ["40.000MHz", "50.000MHz"]
    with pytest.raises(ValueError, match="duplicate"):
        frequency_tags([40e6, 40e6])


# ----------------------------------------------------------------------------- fingerprints

def test_fingerprints_follow_what_stages_read():
    base = stage_fingerprints(small_config("/tmp/x", "imaging.method=prior", "imaging.prior_map=/dev/null"))
    other = stage_fingerprints(small_config("/tmp/x", "imaging.method=prior", "imaging.prior_map=/dev/null",
                                            "products.frame=icrs"))
    assert base["solve"].digest != other["solve"].digest  # the prior map is rotated from products.frame
    assert base["normal"].digest == other["normal"].digest
    assert "products.frame: galactic -> icrs" in other["solve"].explain(base["solve"].record())


def test_reading_an_undeclared_setting_is_refused():
    from mmflow.workflow.engine.fingerprint import ConfigView, UndeclaredConfigRead

    view = ConfigView(small_config("/tmp/x"), ("imaging.eps", "mmode"), "toy")
    assert view.imaging.eps == 0.01 and view.mmode.lmax == 24
    with pytest.raises(UndeclaredConfigRead, match="stage 'toy' reads 'imaging.method'"):
        view.imaging.method
    with pytest.raises(UndeclaredConfigRead):
        view.products


def test_changed_input_file_is_found_and_named(tmp_path):
    from mmflow.workflow.engine.fingerprint import file_digest

    f = tmp_path / "a.uvh5"
    f.write_bytes(b"0123456789")
    d1 = file_digest(f)
    os.utime(f, ns=(d1[1] + 10**9, d1[1] + 10**9))  # touched, same bytes: same digest
    d2 = file_digest(f, {str(f): d1})
    assert d2[2] == d1[2] and d2[1] != d1[1]
    f.write_bytes(b"0123456780")
    assert file_digest(f, {str(f): d2})[2] != d1[2]


# ----------------------------------------------------------------------------- thread budget

def test_thread_budget_divides_usable_cores_among_workers_of_a_host(monkeypatch):
    from mmflow import threads

    monkeypatch.delenv("MMFLOW_THREADS", raising=False)
    monkeypatch.setattr(threads, "usable_cores", lambda: 16)

    class FakeWorker:
        class state:
            nthreads = 2

    import distributed

    monkeypatch.setattr(distributed, "get_worker", lambda: FakeWorker)
    monkeypatch.setenv("MMFLOW_WORKERS_PER_HOST", "4")
    assert threads.n_threads() == 2  # 16 cores / (4 workers x 2 threads)
    monkeypatch.setenv("MMFLOW_WORKERS_PER_HOST", "16")
    assert threads.n_threads() == 1
    monkeypatch.setenv("MMFLOW_THREADS", "3")
    assert threads.n_threads() == 3


def test_usable_cores_follow_affinity():
    from mmflow.threads import usable_cores

    assert 1 <= usable_cores() <= len(os.sched_getaffinity(0))


def test_every_benchmark_name_has_a_module_with_run():
    import importlib
    import inspect

    from mmflow.bench import MODULES
    from mmflow.cli import BENCHMARKS

    assert set(BENCHMARKS) == set(MODULES)
    for what, mod in MODULES.items():
        fn = importlib.import_module(f"mmflow.bench.{mod}").run
        assert list(inspect.signature(fn).parameters)[:2] == ["what", "quick"], what


# ----------------------------------------------------------------------------- one code path, data splits

def test_workflow_alm_equals_engine_alm_and_splits_share_one_transfer_pass(tmp_path):
    """The solve stage and engine.solve_alm are one per-m loop; even/odd halves average to the full data."""
    import zarr

    from mmflow.conventions import healpy_alm
    from mmflow.imaging.solvers import solve_alm
    from mmflow.mmode.engine import accumulate_normal_equations
    from mmflow.mmode.noise import relative_weights
    from mmflow.workflow.pipeline import PIPELINE

    run_dir = tmp_path / "run"
    cfg = small_config(run_dir, "mmode.splits=[full, even, odd]", "observation.integration_s=172.3281810",
                       "imaging.filter_m1_lmin=null", "run.keep=[mmodes.zarr]")
    s = run_workflow(cfg, **QUIET)
    assert s["transfer"]["tasks"] == len(RunDir(run_dir).manifest("transfer")["keys"])  # one pass for 3 splits
    mg = zarr.open_group(str(run_dir / "mmodes.zarr"))
    alm_wf = zarr.open_group(str(run_dir / "alm.zarr"))["alm"][:, 0]  # (split, m, l)
    tel = Context(cfg.model_dump_json(), str(run_dir)).for_stage(PIPELINE.stage("transfer")).telescope()
    acc = accumulate_normal_equations(tel, 40e6, mg["mmodes"][:, 0], 24, relative_weights(mg["inv_var"][0]),
                                      chunk_size=32)
    im = cfg.imaging
    filters = dict(zero_monopole=im.zero_monopole, filter_m0=im.filter_m0, filter_m1_lmin=im.filter_m1_lmin)
    for split in range(3):
        engine = solve_alm(acc, im.eps, filters=filters, split=split)
        wf = healpy_alm(alm_wf[split], 24, 24)
        np.testing.assert_allclose(wf, engine, rtol=0, atol=1e-9 * np.abs(engine).max())
    # V_m(full) = (V_m(even) + V_m(odd)) / 2 exactly for a full day, and the solve is linear
    np.testing.assert_allclose(alm_wf[0], 0.5 * (alm_wf[1] + alm_wf[2]), rtol=0, atol=1e-9 * np.abs(alm_wf[0]).max())
    assert np.abs(alm_wf[1] - alm_wf[2]).max() > 1e-6 * np.abs(alm_wf[0]).max()  # the halves see different noise


def test_nan_in_a_map_is_refused_before_any_file_is_written(ref, tmp_path, monkeypatch):
    from mmflow.imaging import maps

    run_dir = _copy(ref, tmp_path)
    real = maps.alm_to_output_map
    monkeypatch.setattr(maps, "alm_to_output_map", lambda *a, **k: real(*a, **k) * np.inf)
    with pytest.raises(MmflowError, match=r"stage 'products' was about to write \d+ NaN/inf values to maps/map"):
        run_workflow(small_config(run_dir, "products.png=false"), force=True, **QUIET)
    assert not list((run_dir / "maps").glob("*.fits"))


INVARIANCE = """
import hashlib, numpy as np
from mmflow.telescope import Telescope, ovro_lwa_layout
from mmflow.telescope.beams import SinElevationBeam
from mmflow.mmode.engine import accumulate_normal_equations
from mmflow.mmode.gapfill import chunk_mmodes
tel = Telescope(ovro_lwa_layout("core", radius_m=20), SinElevationBeam(1.5), [40e6])
rng = np.random.default_rng(0)
nb = len(tel.antenna_pairs())
acc = accumulate_normal_equations(tel, 40e6, rng.normal(size=(33, 2, nb)) + 1j, 32, dtype=np.float32)
h = hashlib.sha1(b"".join(acc.gram[m].tobytes() + acc.rhs[m].tobytes() for m in acc.ms))
w = (rng.random((300, 20)) > 0.1).astype(float)
res = chunk_mmodes((rng.normal(size=(300, 20)) + 1j) * w, w, 40, rng.uniform(-1e-3, 1e-3, 300), np.full(20, 60),
                   ("full", "even", "odd"), None, 0.5)
h.update(res.mmodes.tobytes() + res.inv_var.tobytes())
print(h.hexdigest())
"""


def test_kernels_give_the_same_bits_for_any_thread_budget():
    """A run resumed on another cluster size gets another per-task thread budget: the bits must not change."""
    out = []
    for threads in ("1", "2"):
        env = dict(os.environ, MMFLOW_THREADS=threads, OPENBLAS_NUM_THREADS="1")  # BLAS as in dask workers
        out.append(subprocess.run([sys.executable, "-c", INVARIANCE], cwd=ROOT, env=env, capture_output=True,
                                  text=True, check=True).stdout.strip())
    assert out[0] == out[1] and len(out[0]) == 40


def test_unflagged_on_grid_fast_path_equals_the_least_squares_fit():
    from mmflow.mmode.gapfill import chunk_mmodes

    rng = np.random.default_rng(3)
    binned = rng.normal(size=(400, 12)) + 1j * rng.normal(size=(400, 12))
    w = np.ones((400, 12))
    args = (binned, w, 60, None, np.full(12, 90), ("full", "even", "odd"), np.ones(12), 0.9)
    fast = chunk_mmodes(*args)
    fit = chunk_mmodes(*args, prior=np.zeros((61, 2, 12), complex))  # a prior forces the fit
    assert fast.fits == [] and fit.fits
    np.testing.assert_allclose(fast.mmodes, fit.mmodes, rtol=0, atol=1e-10 * np.abs(fit.mmodes).max())
    np.testing.assert_array_equal(fast.inv_var, fit.inv_var)
