"""The visibilities released a baseline chunk at a time as the mmodes tasks that read them finish
(mmflow.workflow.engine.release.release_task_chunks): the same m-modes bit for bit, and a run killed after
a task's release resumes without recomputing anything, or recomputes the visibilities first where a task
that read released chunks must run again."""
import shutil

import numpy as np
import pytest
import zarr

from mmflow.workflow.engine.rundir import RunDir
from mmflow.workflow.engine.runner import run_workflow
from tests.workflow_helpers import small_config

UPTO = ["simulate", "mmodes"]
VIS = "vis.zarr/vis"


class Crash(Exception):
    pass


def _arrays(path):
    g = zarr.open_group(str(path), mode="r")
    return {a: arr[:] for a, arr in g.arrays()}


def _same_mmodes(a, b):
    ref, out = _arrays(a / "mmodes.zarr"), _arrays(b / "mmodes.zarr")
    assert ref.keys() == out.keys() and all(np.array_equal(ref[k], out[k]) for k in ref)


def _chunks(run_dir, i):
    """vis.zarr's chunk folders of baseline chunk ``i`` (every time chunk) of the visibilities."""
    return sorted((run_dir / "vis.zarr" / "vis" / "c").glob(f"*/{i}"))


def test_visibilities_go_a_baseline_chunk_at_a_time_and_a_killed_run_resumes(tmp_path, monkeypatch):
    log = []
    ref = tmp_path / "ref"
    s = run_workflow(small_config(ref), only=UPTO, progress=False, log=log.append)
    n = s["mmodes"]["tasks"]
    assert n >= 3
    freed = [m for m in log if "freed" in m and f"of {VIS} " in m]
    assert len(freed) == n and all(f"mmodes's finished tasks b{i:05d} alone" in m for i, m in enumerate(freed))
    rec = RunDir(ref).released("simulate")[VIS]
    assert "by" not in rec and "vis" in rec["arrays"] and not (ref / "vis.zarr" / "vis").exists()  # then all

    real = RunDir.mark_done

    def die_in_task_1(self, stage, key, info, chunks):
        real(self, stage, key, info, chunks)
        if stage == "mmodes" and key == "b00001":
            raise Crash()

    killed = tmp_path / "killed"
    cfg = small_config(killed)
    monkeypatch.setattr(RunDir, "mark_done", die_in_task_1)
    with pytest.raises(Crash):
        run_workflow(cfg, only=UPTO, progress=False, log=lambda *a: None)
    monkeypatch.setattr(RunDir, "mark_done", real)
    # task 0's chunks went as it finished; task 1 finished, killed before its release; task 2 never ran
    assert not _chunks(killed, 0) and _chunks(killed, 1) and _chunks(killed, 2)
    assert RunDir(killed).released("simulate")[VIS]["by"] == {"mmodes": ["b00000"]}
    again = tmp_path / "again"
    shutil.copytree(killed, again)

    log = []
    s = run_workflow(cfg, only=UPTO, progress=False, log=log.append)
    assert not any("recomputing" in m for m in log) and s["mmodes"]["tasks_run"] == n - 2
    assert "simulate" not in s or s["simulate"].get("kept")
    _same_mmodes(ref, killed)
    assert not (killed / "vis.zarr" / "vis").exists() and "by" not in RunDir(killed).released("simulate")[VIS]

    # task 0 forgotten (as --force forgets a damaged one): it reads released chunks, so simulate runs first
    RunDir(again).forget_keys("mmodes", ["b00000"])
    log = []
    run_workflow(small_config(again), only=UPTO, progress=False, log=log.append)
    assert any("[simulate] recomputing: mmodes reads vis.zarr/vis" in m for m in log)
    _same_mmodes(ref, again)
