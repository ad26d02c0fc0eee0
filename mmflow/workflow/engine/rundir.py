"""The run directory: zarr stores per stage, completion markers per chunk, and a lock.

Layout (see docs/data-layout.md)::

    RUN/config.yaml            resolved configuration (+ versions in run.json)
    RUN/vis.zarr ...           one store per stage (declared in mmflow/io/run_stores.py)
    RUN/maps/                  HEALPix FITS, PNGs, summaries (only files mmflow lists are its own)
    RUN/_status/lock           held (flock) by the one driver working in RUN; names host and pid
    RUN/_status/STAGE/         manifest.json (fingerprint, settings, keys), KEY.done markers,
                               chunks.json and complete.json when every key is done, released.json
                               (the stage's stores released once their readers had finished)

A chunk counts as done only when its marker exists: markers are written (atomically) after
the data and list the size and XXH3 checksum of every chunk file the task wrote, so a killed task
is simply redone and a damaged chunk is found (``mmflow verify``). A stage whose
fingerprint (what it reads: settings, inputs' fingerprints, input files) differs from the
stored manifest is stale: mmflow refuses to mix outputs unless asked to recompute
(``--force``), and says which settings or inputs changed.

A store released after its readers finished (:data:`mmflow.io.run_stores.RELEASED_BY_DEFAULT`,
:meth:`RunDir.release`) is recorded in its stage's ``released.json``: the stage stays complete, its
released chunks are not "damaged", and the record goes with the stage (``--force``, a stale stage).
"""
from __future__ import annotations

import fcntl
import json
import os
import shutil
import socket
import time
import uuid
from functools import lru_cache
from pathlib import Path

from mmflow.errors import MmflowError, StaleOutputError
from mmflow.io.stores import dir_size, verify_chunks
from mmflow.paths import expand_path


EXTRA_MARKERS = ["_prepare", "_finalize"]  # what the driver wrote around a stage's tasks


class RunLockedError(MmflowError):
    """Another mmflow driver works in this run directory."""


def _atomic_write(path, text):
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def _under(rel, paths):
    """True where the run-relative chunk path ``rel`` lies in one of ``paths`` (stores or arrays)."""
    return any(rel == q or rel.startswith(q + "/") for q in paths)


def _read_json(path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


class RunDir:
    """Paths, markers and the lock of one run (always an absolute path)."""

    def __init__(self, path):
        self.path = Path(expand_path(path)).absolute()

    def store(self, name):
        return self.path / name

    def status_dir(self, stage):
        return self.path / "_status" / stage

    # ------------------------------------------------------------------------- lock
    @property
    def lock_path(self):
        return self.path / "_status" / "lock"

    def acquire_lock(self):
        """Take the run's exclusive lock; returns ``(file handle, token)``. Released at process exit.

        The kernel releases a ``flock`` when its holder dies, so a killed run leaves no stale
        lock behind; the file's text only says who holds it now.
        """
        self.lock_path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(self.lock_path, "a+")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.seek(0)
            holder = _parse_holder(fh.read())
            fh.close()
            raise RunLockedError(
                f"run directory {self.path} is in use by mmflow on host {holder.get('host', '?')}, pid "
                f"{holder.get('pid', '?')} (since {holder.get('since', '?')}). Fix: wait for that run to "
                f"finish (or stop it), or give this run another run.directory=...") from None
        token = uuid.uuid4().hex
        fh.seek(0)
        fh.truncate()
        fh.write(json.dumps({"host": socket.gethostname(), "pid": os.getpid(), "token": token,
                             "since": time.strftime("%Y-%m-%dT%H:%M:%S")}))
        fh.flush()
        return fh, token

    def release_if_unused(self):
        """Remove the lock file and ``_status`` when the run recorded nothing else there (a run refused
        before any work leaves only its log). Called by the lock's holder before it closes the lock."""
        status = self.lock_path.parent
        if status.is_dir() and [p.name for p in status.iterdir()] == [self.lock_path.name]:
            self.lock_path.unlink()
            status.rmdir()

    def check_holder(self, token):
        """Fail a task whose driver no longer holds the run (another run took the directory over)."""
        if not self.path.is_dir():
            raise MmflowError(f"run directory {self.path} is not visible on host {socket.gethostname()}: "
                              "put it on a filesystem that the driver and every worker share")
        holder = _parse_holder(self.lock_path.read_text() if self.lock_path.exists() else "")
        if token is not None and holder.get("token") != token:
            raise MmflowError(f"run directory {self.path} is now held by another mmflow run "
                              f"(host {holder.get('host')}, pid {holder.get('pid')}); this task stops")

    # ------------------------------------------------------------------------- markers
    def marker(self, stage, key):
        return self.status_dir(stage) / f"{key}.done"

    def is_done(self, stage, key):
        return self.marker(stage, key).exists()

    def mark_done(self, stage, key, info, chunks):
        _atomic_write(self.marker(stage, key), json.dumps({"info": info, "chunks": chunks}, default=str))

    def marker_chunks(self, stage, keys):
        out = {}
        for k in keys:
            m = _read_json(self.marker(stage, k))
            if m:
                out.update(m.get("chunks", {}))
        return out

    def task_infos(self, stage):
        """``{key: info}`` that each finished task of a stage returned."""
        man = self.manifest(stage) or {"keys": []}
        return {k: m["info"] for k in man["keys"] if (m := _read_json(self.marker(stage, k)))}

    def manifest(self, stage):
        return _read_json(self.status_dir(stage) / "manifest.json")

    def is_stale(self, stage, fingerprint):
        """True when the stage has stored outputs made from another fingerprint."""
        old = self.manifest(stage)
        return old is not None and old["fingerprint"] != fingerprint

    def has_results(self, stage):
        """True when the stage has finished a task (its marker exists), its finalize, or completed. A
        stage that has none holds no result (at most the empty stores its prepare made): it may start
        afresh with other settings."""
        man = self.manifest(stage)
        return man is not None and (self.completion(stage) is not None
                                    or any(self.is_done(stage, k) for k in list(man["keys"]) + ["_finalize"]))

    def begin_stage(self, stage, fp, keys, outputs):
        """Write the manifest (or refuse stale outputs); return the keys still to do.

        ``fp`` is a :class:`mmflow.workflow.engine.fingerprint.StageFingerprint`.
        """
        old = self.manifest(stage)
        if old is not None and old["fingerprint"] != fp.digest:
            raise StaleOutputError(
                f"stage '{stage}' in {self.path} was made from other settings or inputs: "
                f"{fp.explain(old)}. Fix: add --force to recompute it and the stages after it, or "
                f"use a new directory with run.directory=...")
        sdir = self.status_dir(stage)
        sdir.mkdir(parents=True, exist_ok=True)
        planned = [k for k in old["keys"] if k not in set(old.get("added_keys", []))] if old else None
        if old is not None and planned != list(keys):
            raise StaleOutputError(f"stage '{stage}' in {self.path}: its chunk keys changed with the same "
                                   f"settings (an older mmflow?). Fix: add --force, or use a new run directory")
        if old is None:
            _atomic_write(sdir / "manifest.json", json.dumps(
                dict(fp.record(), keys=list(keys), outputs=list(outputs),
                     created=time.strftime("%Y-%m-%dT%H:%M:%S")), default=str))
        return [k for k in keys if not self.is_done(stage, k)]

    def add_keys(self, stage, keys):
        """Append work keys discovered while a stage runs (the cycles of an iterative stage)."""
        man = self.manifest(stage)
        new = [k for k in keys if k not in set(man["keys"])]
        if new:
            man["keys"] = list(man["keys"]) + new
            man["added_keys"] = list(man.get("added_keys", [])) + new
            _atomic_write(self.status_dir(stage) / "manifest.json", json.dumps(man, default=str))

    def reset_stage(self, stage):
        """Forget a stage and remove what it wrote: its stores and the files its markers list.

        Nothing else is removed: a file a user put in ``maps/`` stays.
        """
        man = self.manifest(stage)
        if man is None:
            return
        listed = self.marker_chunks(stage, list(man["keys"]) + EXTRA_MARKERS)
        for out in man.get("outputs", []):
            p = self.path / out
            if out.endswith(".zarr") and (p / "zarr.json").exists():
                shutil.rmtree(p)
        for rel in listed:
            p = self.path / rel
            if p.is_file() and not rel.split("/", 1)[0].endswith(".zarr"):
                p.unlink()
        shutil.rmtree(self.status_dir(stage), ignore_errors=True)

    def released(self, stage):
        """``{store: record}`` of the stage's stores released after their readers had finished."""
        return _read_json(self.status_dir(stage) / "released.json") or {}

    def release(self, stage, store):
        """Remove ``store``, written by ``stage``, and record that it was finished and released; returns the
        bytes it held, or None where it is not the run's own store (a link: a prior pass shares its run's
        stores; a directory without the stamp of ``stage``: not written by this run), which stays.

        The record is written first: a kill between the two leaves the record and what is left of the
        store, removed by the next release."""
        p = self.store(store)
        if p.is_symlink() or not p.is_dir():
            return None
        done = self.released(stage)
        if store not in done:  # recorded: its stamp was checked then (a kill may have removed it since)
            stamp = (_read_json(p / "zarr.json") or {}).get("attributes", {}).get("mmflow", {})
            if stamp.get("stage") != stage:
                return None
            done[store] = {"bytes": dir_size(p), "released": time.strftime("%Y-%m-%dT%H:%M:%S")}
            _atomic_write(self.status_dir(stage) / "released.json", json.dumps(done))
        shutil.rmtree(p)
        return done[store]["bytes"]

    def release_arrays(self, stage, unit, paths, by=None):
        """Remove arrays ``paths`` (relative to their store) of the store of ``unit`` (``vis.zarr/vis``: the
        store, then the array's handle), written by ``stage``, and record them under ``unit``; returns the
        bytes they held, or None where the store is not the run's own (as :meth:`release`) or none is left.

        ``paths`` may be chunk folders of the array (``vis/c/0/3``: a part of it), released by the finished
        tasks ``by`` (``{stage: [keys]}``) that alone read them: the record then says so (``by``), and grows with
        each such release; a release without ``by`` (the whole array, once every reader has finished) ends it.
        """
        store = unit.split("/", 1)[0]
        p = self.store(store)
        if p.is_symlink() or not p.is_dir():
            return None
        done = self.released(stage)
        rec = done.get(unit)
        add = [a for a in paths if rec is None or a not in rec["arrays"]]
        if rec is None or add and "by" in rec:
            stamp = (_read_json(p / "zarr.json") or {}).get("attributes", {}).get("mmflow", {})
            if stamp.get("stage") != stage or not paths:
                return None
            rec = dict(rec or {"bytes": 0, "arrays": []}, released=time.strftime("%Y-%m-%dT%H:%M:%S"))
            rec["bytes"] += sum(dir_size(p / a) for a in add)
            rec["arrays"] = rec["arrays"] + add
            rec.pop("by", None)
            if by is not None:
                old = done.get(unit, {}).get("by", {}) if unit in done else {}
                rec["by"] = {s: sorted(set(old.get(s, [])) | set(k)) for s, k in {**old, **by}.items()}
            done[unit] = rec
            _atomic_write(self.status_dir(stage) / "released.json", json.dumps(done))
        for a in rec["arrays"]:
            shutil.rmtree(p / a, ignore_errors=True)
        return rec["bytes"]

    def _gone(self, stage):
        """The run-relative paths the stage's releases removed: whole stores, and arrays (``vis.zarr/vis``)."""
        return tuple(q for unit, rec in self.released(stage).items()
                     for q in ([f"{unit.split('/', 1)[0]}/{a}" for a in rec["arrays"]] if "arrays" in rec else [unit]))

    def keys_writing_released(self, stage):
        """The stage's finished keys (and driver markers) that wrote chunks of its released stores."""
        gone = self._gone(stage)
        man = self.manifest(stage) or {"keys": []}
        return [k for k in list(man["keys"]) + EXTRA_MARKERS if gone and any(
            _under(rel, gone) for rel in self.marker_chunks(stage, [k]))]

    def forget_released(self, stage):
        """Forget the stage's releases (its tasks that wrote them are to run again)."""
        (self.status_dir(stage) / "released.json").unlink(missing_ok=True)

    def _live(self, stage, chunks):
        """``chunks`` less those of the stage's released stores."""
        gone = self._gone(stage)
        return {rel: v for rel, v in chunks.items() if not _under(rel, gone)} if gone else chunks

    def finished_chunks(self, stage):
        """``{relative chunk path: [size, crc]}`` of the stage's finished keys so far (a stage not complete yet,
        whose finished channels the stage run channel by channel with it reads)."""
        man = self.manifest(stage) or {"keys": []}
        return self.marker_chunks(stage, [k for k in list(man["keys"]) + EXTRA_MARKERS if self.is_done(stage, k)])

    def live_chunk_index(self, stage):
        """:meth:`chunk_index` of a complete stage less the chunks of its released stores."""
        return self._live(stage, self.chunk_index(stage))

    def damaged_keys(self, stage):
        """``{key: [problems]}`` of finished keys whose chunk files are missing or truncated (stat only;
        the chunks of released stores are not looked for)."""
        man = self.manifest(stage)
        out = {}
        for k in (list(man["keys"]) + EXTRA_MARKERS if man else []):
            m = _read_json(self.marker(stage, k))
            problems = verify_chunks(self.path, self._live(stage, m.get("chunks", {})), full=False) if m else []
            if problems:
                out[k] = problems
        return out

    def forget_keys(self, stage, keys):
        """Mark keys as not done (their chunks are recomputed) and the stage as incomplete."""
        for k in keys:
            self.marker(stage, k).unlink(missing_ok=True)
        for name in ("complete.json", "chunks.json"):
            (self.status_dir(stage) / name).unlink(missing_ok=True)

    def finish_stage(self, stage, summary):
        """Mark the stage complete, after checking that every key has its marker."""
        man = self.manifest(stage)
        missing = [k for k in man["keys"] if not self.is_done(stage, k)]
        if missing:
            raise MmflowError(f"stage '{stage}': {len(missing)} of {len(man['keys'])} chunks have no completion "
                              f"marker (first: {missing[0]}); it is not complete. Fix: run the same command "
                              "again to compute them")
        chunks = self.marker_chunks(stage, list(man["keys"]) + EXTRA_MARKERS)
        _atomic_write(self.status_dir(stage) / "chunks.json", json.dumps(chunks))
        _atomic_write(self.status_dir(stage) / "complete.json", json.dumps(summary, default=str))

    def stage_summaries(self):
        """``{stage: summary}`` of every stage finished in this run directory, in the order they finished
        (what each recorded when it completed: wall time, tasks, bytes written, peak memory, ...)."""
        done = sorted((p.stat().st_mtime_ns, p.parent.name, p) for p in (self.path / "_status").glob("*/complete.json"))
        return {name: _read_json(p) for _, name, p in done}

    def chunk_index(self, stage):
        """``{relative chunk path: [size, crc]}`` of a complete stage (cached per process)."""
        p = self.status_dir(stage) / "chunks.json"
        if not p.exists():
            raise MmflowError(f"stage '{stage}' in {self.path} is not complete. Fix: run `mmflow run` "
                              f"(or `mmflow {stage}`) first")
        return _load_index(str(p), p.stat().st_mtime_ns)

    def completion(self, stage):
        """The summary the stage recorded when it completed (:meth:`finish_stage`); None if it has not."""
        return _read_json(self.status_dir(stage) / "complete.json")

    def stage_status(self, stage):
        man = self.manifest(stage)
        if man is None:
            return None
        done = sum(1 for k in man["keys"] if self.is_done(stage, k))
        comp = self.completion(stage)
        return {"fingerprint": man["fingerprint"], "done": done, "total": len(man["keys"]),
                "complete": comp is not None, "summary": comp, "released": sorted(self.released(stage))}

    def verify(self, stages, full=True):
        """``{stage: [problems]}`` for every stage with a manifest: missing markers, damaged chunks."""
        out = {}
        for stage in stages:
            man = self.manifest(stage)
            if man is None:
                continue
            problems = [f"chunk key {k}: not done" for k in man["keys"] if not self.is_done(stage, k)]
            problems += verify_chunks(self.path, self._live(stage, self.marker_chunks(
                stage, list(man["keys"]) + EXTRA_MARKERS)), full)
            out[stage] = problems
        return out

    def bytes_of(self, outputs):
        total = 0
        for o in outputs:
            p = self.path / o
            total += p.stat().st_size if p.is_file() else dir_size(p) if p.is_dir() else 0
        return total


def _parse_holder(text):
    try:
        return json.loads(text) if text.strip() else {}
    except ValueError:
        return {}


@lru_cache(maxsize=16)
def _load_index(path, mtime_ns):
    return json.loads(Path(path).read_text())
