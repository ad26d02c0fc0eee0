"""Every zarr store of a run, declared once: arrays, dimensions, dtype, chunks and attributes.

A stage never creates an array by hand: it asks for a store's :class:`StoreSpec` (one
function per store below) and calls :meth:`StoreSpec.create`, which is *create or
validate*: an array that exists with the declared shape, dtype and chunks is kept, one that
is missing is created, one that differs is an error naming the store, the array and the fix.
A ``prepare`` killed half-way through is therefore simply run again.

Writes go through :class:`ChunkLedger`: a task writes chunk-aligned regions and the ledger
records the size and CRC-32 of every chunk file it wrote; the runner puts that list in the
task's completion marker. Readers check those records before they trust a chunk
(:func:`verify_chunks`), so a deleted or truncated chunk is an error naming the file, never
a silent fill value. Every written chunk is materialised on disk (``write_empty_chunks``),
so a missing chunk file always means damage.

Dimensions used below: ``freq`` channels, ``time`` integrations, ``baseline`` pairs,
``m`` orders 0..mmax, ``l`` degrees 0..lmax, ``split`` data splits (full, even, odd, ...),
``group`` fixed baseline groups of the transfer reduction.
"""
from __future__ import annotations

import json
import os
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zarr

from mmflow.errors import InputError, MmflowError

zarr.config.set({"array.write_empty_chunks": True})


class DamagedStoreError(MmflowError):
    """A chunk of a finished stage is missing or differs from what was written."""


@dataclass(frozen=True, eq=False)
class ArraySpec:
    """One array: its name in the store, dimension names, shape, chunk shape, dtype."""

    name: str
    dims: tuple
    shape: tuple
    chunks: tuple
    dtype: str
    fill_value: object = 0
    data: object = None  # small constant arrays are written at creation

    def __post_init__(self):
        if len(self.dims) != len(self.shape) or len(self.chunks) != len(self.shape):
            raise ValueError(f"array spec {self.name}: dims, shape and chunks differ in length")


@dataclass(frozen=True, eq=False)
class StoreSpec:
    """A zarr group of a run directory: its path and its arrays."""

    path: str
    arrays: tuple
    attrs: dict = field(default_factory=dict)

    def create(self, root):
        """Create the store, or validate what exists; returns the open group (``r+``)."""
        location = Path(root) / self.path
        g = zarr.open_group(str(location), mode="a")
        for spec in self.arrays:
            arr = _existing(g, spec.name, location)
            if arr is None:
                if spec.data is not None:
                    g.create_array(spec.name, data=np.asarray(spec.data, spec.dtype), chunks=spec.chunks)
                else:
                    g.create_array(spec.name, shape=spec.shape, chunks=spec.chunks, dtype=spec.dtype,
                                   fill_value=spec.fill_value)
                continue
            _validate(arr, spec, location)
        if self.attrs:
            g.attrs.update(self.attrs)
        return g

    def open(self, root, mode="r"):
        location = Path(root) / self.path
        if not (location / "zarr.json").exists():
            raise InputError(str(location), "store", "missing", "run the stage that writes it first")
        return zarr.open_group(str(location), mode=mode)


def _existing(group, name, location):
    """The array if it exists; a metadata file truncated by a kill is removed and recreated."""
    meta = location / name / "zarr.json"
    if not meta.exists():
        return None
    try:
        json.loads(meta.read_text())
    except ValueError:
        meta.unlink()  # half-written by a killed prepare: mmflow's own file, recreated next
        return None
    return group[name]


def _validate(arr, spec, location):
    got = (tuple(arr.shape), tuple(arr.chunks), np.dtype(arr.dtype))
    want = (tuple(spec.shape), tuple(spec.chunks), np.dtype(spec.dtype))
    if got != want:
        raise InputError(str(location / spec.name), "shape/chunks/dtype",
                         f"stored {got[0]} chunks {got[1]} {got[2]}, the configuration needs "
                         f"{want[0]} chunks {want[1]} {want[2]}",
                         "rerun with --force to rebuild it, or use a new run directory")
    if spec.data is not None and not np.array_equal(arr[...], np.asarray(spec.data, spec.dtype)):
        raise InputError(str(location / spec.name), "values", "stored values differ from this run's",
                         "rerun with --force to rebuild it, or use a new run directory")


# ----------------------------------------------------------------------------- checksums

def chunk_keys(arr, region, aligned=True):
    """Chunk keys (``c/i/j/...``) covered by ``region`` (a tuple of slices; chunk-aligned for writes,
    any region for reads: then every chunk it touches)."""
    ranges = []
    for sl, n, c in zip(_full_region(arr, region), arr.shape, arr.chunks):
        start, stop = sl.start, sl.stop
        if aligned and (start % c or (stop % c and stop != n)):
            raise ValueError(f"region {region} of {arr.path} is not aligned to chunks {arr.chunks}")
        ranges.append(range(start // c, -(-stop // c)))
    if not ranges:
        return ["c"]
    grid = np.stack(np.meshgrid(*ranges, indexing="ij"), -1).reshape(-1, len(ranges))
    return ["c/" + "/".join(map(str, idx)) for idx in grid]


def _full_region(arr, region):
    region = tuple(region) + (slice(None),) * (arr.ndim - len(region))
    return [slice(*s.indices(n)[:2]) for s, n in zip(region, arr.shape)]


def file_crc(path):
    """CRC-32 of a file's bytes (4 GB/s: cheap next to the work that wrote them)."""
    with open(path, "rb") as fh:
        return zlib.crc32(fh.read())


class ChunkLedger:
    """Writes chunk-aligned regions and records ``{relative path: [size, crc32]}`` of each chunk.

    Parameters
    ----------
    root : path of the run directory (recorded paths are relative to it).
    """

    def __init__(self, root):
        self.root = Path(root)
        self.entries = {}
        self.seconds = 0.0  # spent on checksums (reported per task: the bookkeeping's cost)
        self.guard_seconds = 0.0  # spent checking outputs for NaN/inf

    def write(self, group, name, region, data):
        arr = group[name]
        arr[tuple(region) if len(region) else ...] = data
        self.record(arr, region)

    def write_all(self, group, name, data):
        self.write(group, name, (slice(None),) * group[name].ndim, data)

    def record(self, arr, region):
        t0 = time.perf_counter()
        base = Path(arr.store.root) / arr.path
        for key in chunk_keys(arr, region):
            p = base / key
            if not p.exists():
                raise DamagedStoreError(f"{p}: chunk missing right after it was written (is the run "
                                        "directory on a filesystem every worker shares?)")
            self.entries[str(p.relative_to(self.root))] = [p.stat().st_size, file_crc(p)]
        self.seconds += time.perf_counter() - t0

    def record_file(self, path):
        """A plain output file (a FITS map, a PNG)."""
        p = Path(path)
        self.entries[str(p.relative_to(self.root))] = [p.stat().st_size, file_crc(p)]


def verify_chunks(root, entries, full=True):
    """Problems (list of strings) with the recorded chunk files: missing, truncated, changed."""
    problems = []
    for rel, (size, crc) in entries.items():
        p = Path(root) / rel
        if not p.exists():
            problems.append(f"{p}: missing")
        elif p.stat().st_size != size:
            problems.append(f"{p}: {p.stat().st_size} bytes, {size} were written")
        elif full and file_crc(p) != crc:
            problems.append(f"{p}: contents changed (CRC-32 differs)")
    return problems


def check_region(root, index, arr, region, producer):
    """Verify the chunks of ``arr[region]`` against the producing stage's records before reading."""
    base = Path(arr.store.root) / arr.path
    rel_base = base.relative_to(Path(root))
    want = {}
    for key in chunk_keys(arr, region, aligned=False):
        rel = str(rel_base / key)
        if rel not in index:
            raise DamagedStoreError(f"{base / key}: no completion record from stage '{producer}' for this "
                                    f"chunk. Fix: rerun `mmflow {producer} ... --force` (or `mmflow run --force`)")
        want[rel] = index[rel]
    problems = verify_chunks(root, want)
    if problems:
        raise DamagedStoreError(f"stage '{producer}' output is damaged: {problems[0]}"
                                f"{f' (and {len(problems) - 1} more)' if len(problems) > 1 else ''}. "
                                f"Fix: `mmflow verify {root}` lists every damaged chunk; rerun "
                                f"`mmflow run ... --force` to recompute them")


def dir_size(path):
    total = 0
    for dirpath, _, files in os.walk(path):
        total += sum(os.path.getsize(os.path.join(dirpath, f)) for f in files)
    return total
