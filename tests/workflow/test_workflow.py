"""The workflow: demo chain, resumability, staleness, CLI and configuration."""
import json
import os
import re
import signal
import subprocess
import sys

import numpy as np
import pytest
import yaml
from threadpoolctl import threadpool_info, threadpool_limits

from mmflow.cli import main
from mmflow.errors import InputError, MmflowError, StaleOutputError
from mmflow.io.run_stores import STORES
from mmflow.workflow.config.schema import load_config, schema_yaml
from mmflow.workflow.engine.runner import run_workflow, status
from tests.workflow_helpers import ROOT, SMALL, assert_identical, fork_run, interrupt_run, read_outputs, small_config



@pytest.fixture(scope="module")
def reference_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("ref") / "run"
    summaries = run_workflow(small_config(run_dir), progress=False, log=lambda *a: None)
    return run_dir, summaries


def test_demo_chain_produces_maps_and_summaries(reference_run):
    run_dir, summaries = reference_run
    for st in ("simulate", "mmodes", "transfer", "normal", "solve", "products"):
        assert summaries[st]["tasks"] >= 1 and summaries[st]["bytes_written"] > 0
    info = json.loads((run_dir / "maps" / "summary.json").read_text())["maps"][0]
    from mmflow.io.report import check_report  # the run's HTML report: every image decodes, links resolve

    assert check_report(run_dir / "maps" / "report.html") == []
    assert info["unit"] == "K" and info["frame"] == "galactic"
    assert (run_dir / info["fits"]).exists() and (run_dir / info["png"]).exists()
    assert 0 < info["fraction_singular_values_above_sqrt_eps"] <= 1
    cfg_saved = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert cfg_saved["mmode"]["lmax"] == 24
    assert "zarr" in json.loads((run_dir / "run.json").read_text())["versions"]
    st = status(run_dir)
    assert st["products"]["complete"] and st["calibrate"] is None


def test_rerun_skips_everything_and_changes_nothing(reference_run, tmp_path):
    """A finished run run again keeps every stage: no task, no finalize (the maps, the report and
    the recorded stage costs are not rewritten), and says so."""
    run_dir, _ = reference_run
    before = read_outputs(run_dir)
    written = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in [run_dir / "summary.json",
               *(run_dir / "maps").iterdir(), *(run_dir / "_status").glob("*/complete.json")]}
    logged = []
    summaries = run_workflow(small_config(run_dir), progress=False, log=logged.append)
    assert all(s["tasks_run"] == 0 and s["kept"] for s in summaries.values())
    recorded = json.loads((run_dir / "summary.json").read_text())
    assert all(recorded[k]["tasks_run"] == recorded[k]["tasks"] > 0 for k in summaries)  # the run that made them
    assert sum("complete, kept" in m for m in logged) == len(summaries) > 4
    assert_identical(before, read_outputs(run_dir))
    assert {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in written} == written
    assert not (run_dir / "partials.zarr").exists()  # released, and not made again (empty) by a kept prepare


def test_markers_keep_the_names_earlier_versions_gave_them(reference_run):
    """Completion markers are named by the task keys (:mod:`mmflow.workflow.engine.task_key`): run
    directories made by earlier versions resume only while these strings stay as they were. (Since
    2026-11-27 a simulation with a diffuse sky has two phases, its samples ``d{F}_t{B}`` and then
    the time chunks, named as a second phase's are: ``c0000-t00000``.)"""
    from mmflow.workflow.engine.rundir import RunDir

    run_dir, _ = reference_run
    run = RunDir(run_dir)
    keys = {st: run.manifest(st)["keys"] for st in ("simulate", "mmodes", "transfer", "normal", "solve", "products")}
    assert keys["simulate"] == [f"d0_t{b:05d}" for b in range(6)] + ["c0000-t00000", "cycle0000"]
    assert keys["mmodes"][:2] == ["b00000", "b00001"]
    assert keys["transfer"][:2] == ["f0-g0000", "f0-g0001"]
    assert keys["normal"] == keys["solve"] == ["f0-m00000", "f0-m00008", "f0-m00016", "f0-m00024"]
    assert keys["products"] == ["f0"]
    assert all(run.marker(st, k).name == f"{k}.done" and run.is_done(st, k) for st, ks in keys.items() for k in ks)


def test_changed_settings_refuse_stale_outputs_then_force_recomputes(reference_run, tmp_path):
    run_dir = fork_run(reference_run[0], tmp_path / "run", "products")  # a finished run (a copy)
    changed = small_config(run_dir, "imaging.eps=0.1")
    with pytest.raises(StaleOutputError, match="--force"):
        run_workflow(changed, progress=False, log=lambda *a: None)
    run_workflow(changed, only=["solve"], force=True, progress=False, log=lambda *a: None)
    st = status(run_dir)
    assert not st["solve"]["stale"] and st["products"]["stale"] and not st["normal"]["stale"]
    summaries = run_workflow(changed, force=True, progress=False, log=lambda *a: None)
    for upstream in ("simulate", "mmodes", "transfer", "normal", "solve"):  # eps does not touch the Gram
        assert summaries[upstream]["tasks_run"] == 0  # (solve was already recomputed above)
    assert summaries["products"]["tasks_run"] > 0
    assert not any(s["stale"] for s in status(run_dir).values() if s)


def test_calibration_without_long_enough_baselines_stops_before_solving(tmp_path):
    """An explicit cut of 15 wavelengths leaves the small array's antennas without baselines:
    calibrate refuses before any solve, naming the field, the antennas and the fix (``auto``),
    and writes no solution."""
    cfg = small_config(tmp_path / "run", "calibrate.enabled=true", "calibrate.min_baseline_lambda=15")
    with pytest.raises(InputError, match="calibrate.min_baseline_lambda.*antennas keep too few baselines longer "
                                         "than 15 wave.*set calibrate.min_baseline_lambda=auto"):
        run_workflow(cfg, progress=False, log=lambda *a: None)
    assert not (tmp_path / "run" / "gains.zarr").exists()


def test_peeling_without_long_enough_baselines_stops_before_any_fit(tmp_path):
    """Peel's own minimum baseline: without it every fit would be empty (scale 0) and pass silently."""
    cfg = small_config(tmp_path / "run", "peel.enabled=true", "peel.sources=[Cyg A]", "peel.peel=[Cyg A]",
                       "peel.min_baseline_lambda=15")
    with pytest.raises(InputError, match="peel.min_baseline_lambda.*antennas keep too few baselines"
                                         ".*set peel.min_baseline_lambda=auto"):
        run_workflow(cfg, progress=False, log=lambda *a: None)
    assert not (tmp_path / "run" / "peel.zarr").exists()


# the CLI runs compare FITS maps and stores (read_outputs): no PNGs (~2 s of each products stage)
CLI_RUN = [sys.executable, "-m", "mmflow.cli", "run", "workflows/demo.yaml", *SMALL, "products.png=false"]


@pytest.fixture(scope="module")
def cli_reference(tmp_path_factory):
    """An uninterrupted run by the CLI in a subprocess: the same executor as the interrupted runs
    (a process's BLAS thread count, e.g. OPENBLAS_NUM_THREADS, changes floating-point rounding)."""
    run_dir = tmp_path_factory.mktemp("cliref") / "run"
    subprocess.run([*CLI_RUN, f"run.directory={run_dir}", "--no-progress"], cwd=ROOT, check=True,
                   stdout=subprocess.DEVNULL)
    return run_dir


def test_interrupted_run_that_keeps_its_partials_resumes_to_bit_identical_outputs(cli_reference, tmp_path):
    """A run interrupted (SIGINT) in mmodes after its first chunk resumes to the reference's outputs. It
    starts from a copy of the reference's stages before mmodes (:func:`fork_run`). The reference released
    its partials once normal had summed them; this run keeps them (``run.keep``): the same stores and maps
    bit for bit. (A SIGKILL inside transfer: tests/acceptance/test_faults.py, on another cluster size;
    inside solve, after a release: the next test.)"""
    ref_dir, keep = cli_reference, "run.keep=[partials.zarr]"
    run_dir = fork_run(ref_dir, tmp_path / "interrupted", "simulate")
    interrupt_run(run_dir, "mmodes", signal.SIGINT, extra=["products.png=false", keep])
    subprocess.run([*CLI_RUN, keep, f"run.directory={run_dir}", "--no-progress"], cwd=ROOT, check=True,
                   stdout=subprocess.DEVNULL)
    assert (run_dir / "partials.zarr" / "zarr.json").exists() and not (ref_dir / "partials.zarr").exists()
    assert_identical(read_outputs(ref_dir), read_outputs(run_dir))


def _released_after(log_text):
    """``{released unit: the stage that had just finished}`` from a run's log."""
    out, last = {}, None
    for line in log_text.splitlines():
        done = re.search(r"\[(\w+)\] (done in|complete, kept)", line)
        last = done.group(1) if done else last
        gone = re.search(r"\] released (\S+) ", line)
        if gone:
            out[gone.group(1)] = last
    return out


def test_a_run_killed_after_a_release_resumes_bit_identical(cli_reference, tmp_path):
    """The reference released its intermediates (the defaults): the partials once normal had summed them,
    the diffuse sky's samples once simulate had interpolated them, the visibilities, weights and
    autocorrelations once mmodes had read them, the m-modes once transfer had; each recorded with its
    writer (`mmflow status` names them), none counted as damage (a run that keeps them makes the same maps:
    the test above), each released right after the stage the plan names and the arrays left on disk those
    the plan keeps. A run whose normal stage must run again recomputes, first, what it reads through
    released stores (simulate, mmodes, transfer), releases them again, is killed in solve (the stage after
    the release) and resumes to the same bits without recomputing them."""
    import zarr

    from mmflow.io.run_stores import RELEASED_ARRAYS
    from mmflow.workflow.engine.rundir import RunDir
    from mmflow.workflow.engine.runner import verify
    from mmflow.workflow.pipeline import PIPELINE

    ref, out = cli_reference, read_outputs(cli_reference)
    cfg = load_config("workflows/demo.yaml", [*SMALL, f"run.directory={ref}"])
    planned = {**PIPELINE.released(cfg), **PIPELINE.released_arrays(cfg)}
    made = {s: set(RunDir(ref).released(s)) for s in ("simulate", "mmodes", "transfer")}
    assert made == {"simulate": {"diffuse.zarr", "vis.zarr/vis", "vis.zarr/weights", "vis.zarr/autos"},
                    "mmodes": {"mmodes.zarr/mmodes"}, "transfer": {"partials.zarr", "partials.zarr/f0"}}
    after = _released_after((ref / "mmflow.log").read_text())  # partials.zarr/f0: within normal, once summed
    assert {u: after[u] for u in planned if u in after} == {u: planned[u] for u in set().union(*made.values())
                                                            if u in planned}
    for store, arrays in RELEASED_ARRAYS.items():  # what is left: every declared array less those released
        assert not set(arrays) & set(dict(zarr.open_group(str(ref / store), mode="r").arrays()))
    assert not (ref / "partials.zarr").exists() and not (ref / "diffuse.zarr").exists()
    assert "released: diffuse.zarr, vis.zarr/autos, vis.zarr/vis, vis.zarr/weights" in subprocess.run(
        [sys.executable, "-m", "mmflow.cli", "status", str(ref)], cwd=ROOT, check=True, capture_output=True,
        text=True).stdout
    assert not any(verify(ref, full=False).values())
    killed = fork_run(ref, tmp_path / "killed", "transfer")  # normal to do; the partials it reads released
    interrupt_run(killed, "solve", signal.SIGKILL, extra=["products.png=false"])
    log = (killed / "mmflow.log").read_text()
    assert "[transfer] recomputing: normal reads partials.zarr" in log
    assert "[mmodes] recomputing: transfer reads mmodes.zarr/mmodes" in log and "[simulate] recomputing: mmodes" in log
    assert not (killed / "partials.zarr").exists() and RunDir(killed).released("transfer")
    assert set(RunDir(killed).released("simulate")) == made["simulate"]
    assert status(killed)["normal"]["complete"] and not status(killed)["solve"]["complete"]
    resumed = subprocess.run([*CLI_RUN, f"run.directory={killed}", "--no-progress"], cwd=ROOT, check=True,
                             capture_output=True, text=True).stdout
    assert "[transfer] complete, kept" in resumed and "recomputing" not in resumed, resumed
    assert_identical(out, read_outputs(killed))
    assert not (killed / "partials.zarr").exists()


def test_a_single_stage_that_needs_a_released_store_is_refused_naming_the_fix(reference_run, tmp_path):
    """``mmflow normal`` alone cannot remake the partials it reads, released after the normal stage that
    made the reference: refused before any work, naming `mmflow run` and run.keep; nothing recomputed."""
    from mmflow.errors import MmflowError

    run_dir = fork_run(reference_run[0], tmp_path / "run", "transfer")
    with pytest.raises(MmflowError, match=r"reads partials.zarr.*mmflow run.*run.keep=\[partials.zarr\]"):
        run_workflow(small_config(run_dir), only=["normal"], progress=False, log=lambda *a: None)
    assert status(run_dir)["transfer"]["complete"] and status(run_dir)["normal"] is None


def test_the_interrupt_helper_fails_when_the_child_never_reaches_the_stage(tmp_path):
    """A run refused before any work is not "interrupted and resumed": the helper says so."""
    with pytest.raises(AssertionError, match=r"ended \(exit 2\) before stage 'transfer'"):
        interrupt_run(tmp_path / "refused", "transfer", signal.SIGKILL, extra=["mmode.lmax=-1"])


def test_single_stage_subcommand_needs_its_inputs(tmp_path, capsys):
    rc = main(["solve", "workflows/demo.yaml", *SMALL, f"run.directory={tmp_path / 'r'}"])
    assert rc == 2
    assert "stage 'solve' needs stage 'simulate' complete" in capsys.readouterr().err


def test_version_and_non_stage_commands_do_not_import_the_stages():
    """`mmflow --version` (and the other commands that are not a stage) parse without listing the
    stages, whose import costs ~3 s; a stage command still finds its stage."""
    import subprocess
    import sys

    code = ("import sys; from mmflow.cli import build_parser, main\n"
            "try:\n    main(['--version'])\nexcept SystemExit:\n    pass\n"
            "print('stages imported:', 'mmflow.workflow.pipeline' in sys.modules)\n"
            "print(build_parser().parse_args(['solve', 'w.yaml']).cmd)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    from mmflow import __version__

    assert out.splitlines() == [f"mmflow {__version__}", "stages imported: False", "solve"], out


def test_reading_and_checking_a_workflow_imports_no_numerical_stack():
    """``mmflow config show/init`` and every command that reads a workflow parse and check it without
    the kernels' heavy imports (healpy + matplotlib ~1 s, numba ~0.4 s: measured 2.0 -> 0.45 s)."""
    import subprocess
    import sys

    code = ("import sys; from mmflow.workflow.config.schema import load_config\n"
            "load_config('workflows/demo-calibrate.yaml', ['imaging.method=tikhonov'])\n"
            "print(sorted(m for m in ('healpy', 'numba', 'matplotlib', 'ducc0', 'mmflow.mmode.transfer') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_config_schema_overrides_and_errors(tmp_path, capsys):
    text = schema_yaml()
    assert "eps: 0.01" in text and "lmax: 64" in text
    assert main(["config", "init", str(tmp_path / "w.yaml")]) == 0
    cfg = load_config(tmp_path / "w.yaml", ["mmode.lmax=99", "observation.freqs_mhz=[50, 60]"])
    assert cfg.mmode.lmax == 99 and cfg.observation.freqs_mhz == [50, 60]
    assert cfg.run.directory.endswith("runs/w")  # its own run directory, not the demo's
    before = (tmp_path / "w.yaml").read_text()
    assert main(["config", "init", str(tmp_path / "w.yaml")]) == 2  # never overwrites
    assert (tmp_path / "w.yaml").read_text() == before and "exists already" in capsys.readouterr().err
    assert main([]) == 0 and "usage: mmflow" in capsys.readouterr().out  # bare mmflow: the help
    with pytest.raises(SystemExit):
        main(["--version"])
    assert capsys.readouterr().out.startswith("mmflow ")
    assert main(["status", str(tmp_path / "no-such-run")]) == 2
    assert "does not exist" in capsys.readouterr().err
    with pytest.raises(InputError, match=r"mmode.lmaxx.*Extra inputs"):
        load_config("workflows/demo.yaml", ["mmode.lmaxx=3"])
    with pytest.raises(InputError, match="freqs_mhz"):
        load_config("workflows/demo.yaml", ["observation.freqs_mhz=[-1]"])
    with pytest.raises(InputError, match="without '='"):
        load_config("workflows/demo.yaml", ["mmode.lmax"])
    with pytest.raises(InputError, match="file not found"):
        load_config(tmp_path / "missing.yaml")
    assert main(["status", str(tmp_path)]) == 0
    assert "not started" in capsys.readouterr().out
    (tmp_path / "config.yaml").write_text("imaging: {noise_weighting: true}\n")  # an older mmflow's key
    assert main(["status", str(tmp_path)]) == 0


def test_shipped_workflows_validate():
    import glob

    names = sorted(os.path.basename(p)[:-5] for p in glob.glob(os.path.join(ROOT, "workflows", "*.yaml")))
    assert {"demo", "uvh5-image", "ovro-lwa-2017", "ovro-lwa-stage3", "paper-scale", "hpc-slurm"} <= set(names)
    for name in names:
        cfg = load_config(os.path.join(ROOT, "workflows", f"{name}.yaml"))
        assert cfg.run.name, name
    paper = load_config(os.path.join(ROOT, "workflows", "ovro-lwa-2017.yaml"))
    assert paper.mmode.lmax == 1000 and paper.imaging.eps == 0.01 and len(paper.observation.freqs_mhz) == 8
    assert paper.imaging.filter_m1_lmin == 100
    # the paper's recipe on raw files: calibration on the 22-min Cyg A / Cas A track, peel, terrestrial
    assert paper.source == "ingest" and paper.calibrate.enabled and paper.calibrate.track_min == 22.0
    assert paper.calibrate.sources == ["Cyg A", "Cas A"] and paper.peel.enabled and paper.terrestrial.enabled
    stage3 = load_config(os.path.join(ROOT, "workflows", "ovro-lwa-stage3.yaml"))
    assert stage3.telescope.preset == "full" and stage3.calibrate.enabled


def test_docs_configuration_page_matches_schema():
    with open(os.path.join(ROOT, "docs", "configuration.md")) as fh:
        doc = fh.read()
    assert schema_yaml().strip() in doc, "regenerate docs/configuration.md with `mmflow config show`"


def test_docker_files_are_consistent():
    with open(os.path.join(ROOT, "docker", "compose.yaml")) as fh:
        compose = yaml.safe_load(fh)
    svc = compose["services"]
    assert {"scheduler", "worker", "client"} <= set(svc)
    published = [re.sub(r"\$\{(\w+):-([^}]*)\}", lambda m: m.group(2), p)
                 for p in svc["scheduler"]["ports"]]  # compose's ${VAR:-default}, VAR unset
    assert sorted(published) == ["127.0.0.1:8786:8786", "127.0.0.1:8787:8787"]  # loopback unless opted in
    assert all(p.startswith("${MMFLOW_BIND_ADDRESS:-127.0.0.1}:") for p in svc["scheduler"]["ports"])
    assert "tcp://scheduler:8786" in " ".join(svc["worker"]["command"])
    assert svc["client"]["environment"]["DASK_SCHEDULER_ADDRESS"] == "tcp://scheduler:8786"
    assert any(v.endswith(":/runs") for v in svc["worker"]["volumes"])
    with open(os.path.join(ROOT, "docker", "Dockerfile")) as fh:
        df = fh.read()
    assert df.startswith("#") and "FROM python:3.11" in df and "pip install ." in df
    for path in ("pyproject.toml", "mmflow", "workflows"):
        assert f"COPY {path}" in df and os.path.exists(os.path.join(ROOT, path))
    cmd = svc["client"]["command"]
    assert cmd[:2] == ["mmflow", "run"] and cmd[2].startswith("/opt/mmflow/workflows/")
    assert os.path.exists(os.path.join(ROOT, "workflows", os.path.basename(cmd[2])))


def test_radiometer_noise_matches_data_noise_and_store_mode_writes_the_kernel_blocks(tmp_path):
    """Two noise models agree on the simulated (radiometer-noise) data; stored B equals the kernel."""
    import zarr

    from mmflow.mmode.engine import GridCache, chunk_blocks, plan_chunks
    from mmflow.workflow.engine.context import Context

    run_dir = tmp_path / "run"
    quiet = ["telescope.radius_m=10", "observation.integration_s=13.0", "sky.sources=[]", "transfer.mode=store"]
    upto_mmodes = ["simulate", "mmodes"]
    cfg = small_config(run_dir, *quiet, "mmode.noise=data")  # the residual of each baseline's band-limited fit
    run_workflow(cfg, only=upto_mmodes + ["transfer"], progress=False, log=lambda *a: None)
    data_iv = zarr.open_group(str(run_dir / "mmodes.zarr"), mode="r")["inv_var"][0]
    # the same simulated data (a copy of the first run's), their m-modes weighted by the radiometer equation
    cfg2 = small_config(fork_run(run_dir, tmp_path / "run2", "simulate"), *quiet, "mmode.noise=radiometer")
    run_workflow(cfg2, only=upto_mmodes, progress=False, log=lambda *a: None)
    radio_iv = zarr.open_group(str(tmp_path / "run2" / "mmodes.zarr"), mode="r")["inv_var"][0]
    vis = zarr.open_group(str(run_dir / "vis.zarr"), mode="r")
    pairs, enu = vis["pairs"][:], vis["antenna_enu"][:]
    length = np.linalg.norm(enu[pairs[:, 1]] - enu[pairs[:, 0]], axis=1)
    cross = length > 0
    for part in (cross & (length <= np.median(length[cross])), cross & (length > np.median(length[cross]))):
        ratio = np.median(data_iv[part] / radio_iv[part])
        assert abs(ratio - 1) < 0.05, ratio  # injected radiometer noise recovered on short and long baselines
    # noiseless data: radiometer weights (the default where autocorrelations exist) are equal across lengths
    # (250 integrations, the SMALL configuration's: the weights' equality depends on no integration count)
    run_workflow(small_config(tmp_path / "run3", *quiet, "sky.noise=false", "observation.integration_s=344.6563620"),
                 only=upto_mmodes,
                 progress=False, log=lambda *a: None)
    iv = zarr.open_group(str(tmp_path / "run3" / "mmodes.zarr"), mode="r")["inv_var"][0][cross]
    assert iv.max() / iv.min() - 1 < 0.01
    from mmflow.workflow.pipeline import PIPELINE

    tel = Context(cfg.model_dump_json(), str(run_dir)).for_stage(PIPELINE.stage("transfer")).telescope()
    chunks, lmax_b = plan_chunks(tel, 40e6, 24, 32)
    assert len(chunks) >= 1
    tg = zarr.open_group(str(run_dir / "transfer.zarr" / "f0"), mode="r")
    order = tg["order"][:]
    assert np.array_equal(np.sort(order), np.arange(len(order)))
    blocks = dict(chunk_blocks(tel, 40e6, chunks[-1], 24, lmax_b, np.float64, GridCache(tel, 40e6)))
    rows = slice((len(chunks) - 1) * 32, (len(chunks) - 1) * 32 + len(chunks[-1].index))
    for m in (0, 3, 17):
        stored = tg[f"B_m{m:05d}"][:, rows, :]
        n = len(chunks[-1].index)
        np.testing.assert_array_equal(stored[0], blocks[m][:n])
        if m > 0:
            np.testing.assert_array_equal(stored[1], blocks[m][n:])


def test_every_task_runs_its_blas_on_one_thread_whatever_the_process_has(tmp_path):
    """A synchronous run in a process whose BLAS runs two threads (a user's session) runs each task's BLAS
    on one thread, as a dask worker's (:func:`mmflow.threads.blas_on_one_thread`; the task markers record
    it), and gives the process its threads back. OpenBLAS's GEMM on two threads rounds otherwise than on
    one, and a batch job's workers inherit the submitting shell's ``OPENBLAS_NUM_THREADS``: the SLURM
    tier's runs differed from their synchronous references in the last bit of their Grams.
    (The SLURM tier checks its workers: tests/cluster/test_slurm_cluster.py.)"""
    from mmflow.workflow.engine.rundir import RunDir

    with threadpool_limits(2, user_api="blas"):
        run_workflow(small_config(tmp_path / "run"), only=["simulate", "mmodes"], progress=False,
                     log=lambda *a: None)
        assert {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"} == {2}
    infos = [i for st in ("simulate", "mmodes") for i in RunDir(tmp_path / "run").task_infos(st).values()
             if "threads" in i]  # the tasks' records (not a pass's)
    assert len(infos) >= 2 and [i["blas_threads"] for i in infos] == [1] * len(infos)
    assert [i["tasks_at_once"] for i in infos] == [1] * len(infos)  # a synchronous run: each task's peaks its own


def test_every_store_records_config_versions_and_fingerprint(reference_run):
    import zarr

    run_dir, _ = reference_run
    for store in ("vis.zarr", "mmodes.zarr", "normal.zarr", "alm.zarr"):  # partials.zarr: released after normal
        meta = zarr.open_group(str(run_dir / store), mode="r").attrs["mmflow"]
        assert meta["config"]["mmode"]["lmax"] == 24 and meta["versions"]["numpy"]
        assert meta["fingerprint"] == status(run_dir)[meta["stage"]]["fingerprint"]


def test_a_stage_task_opens_each_store_once_and_still_checks_every_chunk(reference_run, monkeypatch):
    """A task's context keeps the groups and arrays it opened (zarr reads their metadata through its
    I/O thread, ~1 ms each): reading two regions of one array opens the store once; every chunk read
    is still checked against the producer's records, and the checksum time is counted once (the times: an
    array the run keeps, its visibilities released after mmodes)."""
    import zarr

    from mmflow.io import stores
    from mmflow.workflow.engine.context import Context
    from mmflow.workflow.pipeline import PIPELINE

    run_dir, _ = reference_run
    opened = []
    real_open = zarr.open_group
    monkeypatch.setattr(stores.zarr, "open_group", lambda *a, **k: opened.append(1) or real_open(*a, **k))
    cfg = small_config(run_dir)
    ctx = Context(cfg.model_dump_json(), str(run_dir)).for_stage(PIPELINE.stage("mmodes"))
    task = ctx.for_task(keep_handles=True)
    a, b = task.read(STORES.vis.lst, (slice(0, 3),)), task.read(STORES.vis.lst, (slice(3, 6),))
    assert len(opened) == 1 and a.shape[0] == b.shape[0] == 3
    store_total = task.open("vis.zarr").store.seconds  # the kept store's running total of checksum time
    assert 0 < store_total and task.ledger.seconds == pytest.approx(store_total, rel=1e-9)  # counted once
    plain = ctx.for_task()  # outside a stage task (prepare, finalize): opened each time
    plain.read(STORES.vis.lst, (slice(0, 3),)), plain.read(STORES.vis.lst, (slice(3, 6),))
    assert len(opened) == 3
    with pytest.raises(MmflowError, match="writes vis.zarr's array 'lst' into .*mmodes.zarr"):
        task.write(task.open(STORES.mmodes, mode="r+"), STORES.vis.lst, (slice(0, 1),), np.zeros(1))  # refused
    chunk = next((run_dir / "vis.zarr" / "lst" / "c").rglob("*"), None)
    while chunk is not None and chunk.is_dir():
        chunk = next(chunk.iterdir())
    data = chunk.read_bytes()
    chunk.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))  # a damaged chunk is found through a kept handle
    try:
        with pytest.raises(stores.DamagedStoreError, match="checksum differs"):
            task.read(STORES.vis.lst, (slice(None),))
    finally:
        chunk.write_bytes(data)
