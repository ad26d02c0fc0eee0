"""The run directory: zarr stores per stage and completion markers per chunk.

Layout (see docs/data-layout.md)::

    RUN/config.yaml            resolved configuration (+ versions in run.json)
    RUN/vis.zarr               visibilities (time x baseline x frequency), weights, LSTs
    RUN/mmodes.zarr            m-modes (frequency x m x 2 x baseline), noise weights
    RUN/normal.zarr            G_m, r_m, v^H v per frequency and m block
    RUN/alm.zarr               solved a_lm per frequency, L-curves, singular-value fractions
    RUN/maps/                  HEALPix FITS, Mollweide PNG, summary.json
    RUN/_status/STAGE/         manifest.json (fingerprint, keys), KEY.done markers, complete.json

A chunk counts as done only when its marker exists: markers are written (atomically) after
the data, so a killed task is simply redone. A stage whose fingerprint (its config and its
inputs' fingerprints) differs from the stored manifest is stale: mmflow refuses to mix
outputs unless asked to recompute (``--force``).
"""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

from mmflow.errors import StaleOutputError


def _atomic_write(path, text):
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


class RunDir:
    """Paths and markers of one run."""

    def __init__(self, path):
        self.path = Path(path)

    def store(self, name):
        return self.path / name

    def status_dir(self, stage):
        return self.path / "_status" / stage

    def marker(self, stage, key):
        return self.status_dir(stage) / f"{key}.done"

    def is_done(self, stage, key):
        return self.marker(stage, key).exists()

    def mark_done(self, stage, key, info=None):
        _atomic_write(self.marker(stage, key), json.dumps(info or {}, default=str))

    def manifest(self, stage):
        p = self.status_dir(stage) / "manifest.json"
        return json.loads(p.read_text()) if p.exists() else None

    def is_stale(self, stage, fingerprint):
        """True when the stage has stored outputs made from another fingerprint."""
        old = self.manifest(stage)
        return old is not None and old["fingerprint"] != fingerprint

    def begin_stage(self, stage, fingerprint, keys, outputs):
        """Write the manifest (or refuse stale outputs); return the keys still to do."""
        if self.is_stale(stage, fingerprint):
            raise StaleOutputError(
                f"stage '{stage}' in {self.path} was made from other inputs or settings "
                f"(stored {self.manifest(stage)['fingerprint']}, now {fingerprint}): rerun with --force to "
                f"recompute it (and the stages after it), or use a new run directory")
        sdir = self.status_dir(stage)
        sdir.mkdir(parents=True, exist_ok=True)
        if self.manifest(stage) is None:
            _atomic_write(sdir / "manifest.json", json.dumps(
                {"fingerprint": fingerprint, "keys": list(keys), "outputs": list(outputs),
                 "created": time.strftime("%Y-%m-%dT%H:%M:%S")}))
        return [k for k in keys if not self.is_done(stage, k)]

    def reset_stage(self, stage, outputs):
        shutil.rmtree(self.status_dir(stage), ignore_errors=True)
        for o in outputs:
            p = self.path / o
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()

    def finish_stage(self, stage, summary):
        _atomic_write(self.status_dir(stage) / "complete.json", json.dumps(summary, default=str))

    def stage_status(self, stage):
        man = self.manifest(stage)
        if man is None:
            return None
        done = sum(1 for k in man["keys"] if self.is_done(stage, k))
        comp = self.status_dir(stage) / "complete.json"
        return {"fingerprint": man["fingerprint"], "done": done, "total": len(man["keys"]),
                "complete": comp.exists(), "summary": json.loads(comp.read_text()) if comp.exists() else None}

    def bytes_of(self, outputs):
        total = 0
        for o in outputs:
            p = self.path / o
            if p.is_file():
                total += p.stat().st_size
            elif p.is_dir():
                total += sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
        return total
