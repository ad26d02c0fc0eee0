"""transfer and normal channel by channel (mmflow.workflow.engine.channels): each channel's partials summed,
then released, before the next channel's are made; a run killed after a channel's release resumes to the
same normal equations bit for bit, recomputing nothing."""
import numpy as np
import pytest
import zarr

from mmflow.workflow.engine.channels import channel_of
from mmflow.workflow.engine.rundir import RunDir
from mmflow.workflow.engine.runner import run_workflow
from tests.workflow_helpers import fork_run, small_config

TWO = ["observation.freqs_mhz=[40.0, 50.0]", "mmode.splits=[full]", "run.keep=[mmodes.zarr]"]
UPTO = ["simulate", "mmodes", "transfer", "normal"]


class Crash(Exception):
    pass


def _arrays(path):
    g = zarr.open_group(str(path), mode="r")
    return {f"{n}/{a}": arr[:] for n, sub in [("", g), *g.groups()] for a, arr in sub.arrays()}


def test_transfer_and_normal_alternate_by_channel_and_resume_after_a_release(tmp_path, monkeypatch):
    real, done = RunDir.mark_done, []

    def record(self, stage, key, info, chunks):
        real(self, stage, key, info, chunks)
        if stage in ("transfer", "normal") and not key.startswith("_"):
            done.append((stage, channel_of(key)))

    monkeypatch.setattr(RunDir, "mark_done", record)
    log = []
    run_workflow(small_config(tmp_path / "ref", *TWO), only=UPTO, progress=False, log=log.append)
    # channel 0 of transfer, then of normal, then channel 1 of each: never a channel's partials before
    # the previous channel's have been summed
    assert [s for i, s in enumerate(done) if i == 0 or s != done[i - 1]] == [
        ("transfer", 0), ("normal", 0), ("transfer", 1), ("normal", 1)]
    gone = [m for m in log if "released partials.zarr/f" in m]
    assert len(gone) == 2 and "channel 0, summed by normal" in gone[0]
    assert set(RunDir(tmp_path / "ref").released("transfer")) == {"partials.zarr", "partials.zarr/f0",
                                                                   "partials.zarr/f1"}

    def die_in_channel_1(self, stage, key, info, chunks):
        real(self, stage, key, info, chunks)
        if stage == "transfer" and not key.startswith("_") and channel_of(key) == 1:
            raise Crash()

    killed = fork_run(tmp_path / "ref", tmp_path / "killed", "mmodes")
    cfg = small_config(killed, *TWO)
    monkeypatch.setattr(RunDir, "mark_done", die_in_channel_1)
    with pytest.raises(Crash):
        run_workflow(cfg, only=UPTO, progress=False, log=lambda *a: None)
    assert not (killed / "partials.zarr" / "f0").exists() and (killed / "partials.zarr" / "f1").exists()
    assert list(RunDir(killed).released("transfer")) == ["partials.zarr/f0"]
    monkeypatch.setattr(RunDir, "mark_done", real)
    log = []
    s = run_workflow(cfg, only=UPTO, progress=False, log=log.append)
    assert not any("recomputing" in m for m in log) and s["transfer"]["tasks_run"] < s["transfer"]["tasks"]
    ref, out = _arrays(tmp_path / "ref" / "normal.zarr"), _arrays(killed / "normal.zarr")
    assert ref.keys() == out.keys() and all(np.array_equal(ref[k], out[k]) for k in ref)
    assert not (killed / "partials.zarr").exists()
