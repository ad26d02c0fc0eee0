"""The run directory's releases: only the run's own store goes, recorded first; its chunks are then no damage."""
import json

from mmflow.workflow.engine.rundir import RunDir


def _store(path, stage=None):
    """A zarr group's directory with one chunk file, stamped by ``stage`` as the runner stamps its stores."""
    (path / "a" / "c").mkdir(parents=True)
    (path / "a" / "c" / "0").write_bytes(b"x" * 100)
    attrs = {"mmflow": {"stage": stage}} if stage else {}
    (path / "zarr.json").write_text(json.dumps({"zarr_format": 3, "node_type": "group", "attributes": attrs}))


def test_release_removes_only_the_run_s_own_store_and_records_it(tmp_path):
    run = RunDir(tmp_path / "run")
    run.status_dir("transfer").mkdir(parents=True)
    _store(run.store("partials.zarr"), "transfer")
    _store(tmp_path / "other.zarr", "transfer")
    (run.path / "linked.zarr").symlink_to(tmp_path / "other.zarr")  # a prior pass's link to its run's store
    _store(run.store("mine.zarr"))  # no stamp: not written by this run
    _store(run.store("norm.zarr"), "normal")  # another stage's
    assert run.release("transfer", "linked.zarr") is None and (tmp_path / "other.zarr" / "zarr.json").exists()
    assert run.release("transfer", "mine.zarr") is None and run.store("mine.zarr").exists()
    assert run.release("transfer", "norm.zarr") is None and run.store("norm.zarr").exists()
    assert run.released("transfer") == {}
    nbytes = run.release("transfer", "partials.zarr")
    assert nbytes > 100 and not run.store("partials.zarr").exists()
    assert run.released("transfer")["partials.zarr"]["bytes"] == nbytes
    (run.store("partials.zarr") / "a").mkdir(parents=True)  # what a kill during the removal left, unstamped
    assert run.release("transfer", "partials.zarr") == nbytes and not run.store("partials.zarr").exists()


def test_chunks_of_a_released_store_are_not_damage(tmp_path):
    run = RunDir(tmp_path / "run")
    _store(run.store("partials.zarr"), "transfer")
    _store(run.store("transfer.zarr"), "transfer")
    chunks = {f"{s}/a/c/0": [100, "0"] for s in ("partials.zarr", "transfer.zarr")}
    run.status_dir("transfer").mkdir(parents=True)
    (run.status_dir("transfer") / "manifest.json").write_text(json.dumps({"fingerprint": "f", "keys": ["k"]}))
    run.mark_done("transfer", "k", {}, chunks)
    run.release("transfer", "partials.zarr")
    assert run.damaged_keys("transfer") == {} and run.keys_writing_released("transfer") == ["k"]
    (run.store("transfer.zarr") / "a" / "c" / "0").unlink()  # a kept store's chunk: still damage
    assert list(run.damaged_keys("transfer")) == ["k"]
    run.forget_released("transfer")
    assert run.released("transfer") == {} and len(run.damaged_keys("transfer")["k"]) == 2


def test_release_of_arrays_removes_them_alone_and_their_chunks_are_not_damage(tmp_path):
    """Arrays of a kept store go alone, recorded under ``store/array``; the store and its other arrays stay
    (their chunks still checked); a linked store (a prior pass's) keeps its arrays."""
    run = RunDir(tmp_path / "run")
    _store(run.store("vis.zarr"), "simulate")
    (run.store("vis.zarr") / "vis" / "c").mkdir(parents=True)
    (run.store("vis.zarr") / "vis" / "zarr.json").write_text("{}")
    (run.store("vis.zarr") / "vis" / "c" / "0").write_bytes(b"x" * 200)
    chunks = {"vis.zarr/a/c/0": [100, "0"], "vis.zarr/vis/c/0": [200, "0"]}
    run.status_dir("simulate").mkdir(parents=True)
    (run.status_dir("simulate") / "manifest.json").write_text(json.dumps({"fingerprint": "f", "keys": ["k"]}))
    run.mark_done("simulate", "k", {}, chunks)
    assert run.release_arrays("simulate", "vis.zarr/vis", ["vis"]) >= 200
    assert not (run.store("vis.zarr") / "vis").exists() and (run.store("vis.zarr") / "a" / "c" / "0").exists()
    assert run.released("simulate")["vis.zarr/vis"]["arrays"] == ["vis"]
    assert run.damaged_keys("simulate") == {} and run.keys_writing_released("simulate") == ["k"]
    (run.store("vis.zarr") / "a" / "c" / "0").unlink()  # a kept array's chunk: still damage
    assert run.damaged_keys("simulate")["k"] == [f"{run.path}/vis.zarr/a/c/0: missing"]
    _store(tmp_path / "other.zarr", "mmodes")
    (run.path / "mmodes.zarr").symlink_to(tmp_path / "other.zarr")
    assert run.release_arrays("mmodes", "mmodes.zarr/a", ["a"]) is None and (tmp_path / "other.zarr" / "a").exists()
