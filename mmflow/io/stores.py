"""Every zarr store of a run, declared once: arrays, dimensions, dtype, chunks and attributes.

A stage never creates an array by hand: it asks for a store's :class:`StoreSpec` (one
function per store below) and calls :meth:`StoreSpec.create`, which is *create or
validate*: an array that exists with the declared shape, dtype and chunks is kept, one that
is missing is created, one that differs is an error naming the store, the array and the fix.
A ``prepare`` killed half-way through is therefore simply run again.

Writes go through :class:`ChunkLedger`: a task writes chunk-aligned regions and the ledger
records the size and XXH3 checksum of every chunk file it wrote (computed by :class:`CheckedStore`
as the bytes pass, so no file is read back); the runner puts that list in the task's
completion marker. Reads through a :class:`CheckedStore` check every chunk against those
records as zarr reads it, so a deleted, truncated or altered chunk is an error naming the
file, never a silent fill value, and no chunk is read twice. Every written chunk is
materialised on disk (``write_empty_chunks``), so a missing chunk file always means damage;
:func:`verify_chunks` checks files at rest (``mmflow verify``).

The stores themselves, their dimensions (:data:`mmflow.io.run_stores.DIMENSIONS`) and the
meaning of every array (each spec's ``doc``) are declared in :mod:`mmflow.io.run_stores`;
``docs/stores.md`` is generated from them (``mmflow stores show``).
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import xxhash
import zarr
from zarr.storage import LocalStore

from mmflow.errors import InputError, MmflowError

zarr.config.set({"array.write_empty_chunks": True})


class DamagedStoreError(MmflowError):
    """A chunk of a finished stage is missing or differs from what was written."""


@dataclass(frozen=True, eq=False)
class ArraySpec:
    """One array: its name in the store, dimension names, shape, chunk shape, dtype, and ``doc``:
    what it holds (units, conventions), rendered into ``docs/stores.md``."""

    name: str
    dims: tuple
    shape: tuple
    chunks: tuple
    dtype: str
    fill_value: object = 0
    data: object = None  # small constant arrays are written at creation
    doc: str = ""
    #: False: chunks stored as raw bytes. For arrays re-read many times whose content zstd barely
    #: shrinks: CLEAN's complex128 Cholesky factors decode at ~150 MB/s, 5-8x slower than raw reads
    compressed: bool = True

    def __post_init__(self):
        if len(self.dims) != len(self.shape) or len(self.chunks) != len(self.shape):
            raise ValueError(f"array spec {self.name}: dims, shape and chunks differ in length")


@dataclass(frozen=True, eq=False)
class StoreSpec:
    """A zarr group of a run directory: its path, its arrays, its attributes and ``doc``: which
    stage writes it and what it holds, rendered into ``docs/stores.md``."""

    path: str
    arrays: tuple
    attrs: dict = field(default_factory=dict)
    doc: str = ""

    @property
    def nbytes(self):
        """Uncompressed bytes of every array: an upper bound of the store's size on disk."""
        return int(sum(np.prod(a.shape, dtype=float) * np.dtype(a.dtype).itemsize for a in self.arrays))

    @property
    def n_files(self):
        """Files the store holds when every chunk is written: per array ``prod(ceil(shape / chunks))``
        chunk files and its ``zarr.json``, and the group's ``zarr.json`` (zarr v3, one file a chunk).
        What a shared file system's metadata servers count (Lustre, GPFS): ``docs/clusters.md``."""
        return 1 + sum(1 + math.prod(-(-n // max(c, 1)) for n, c in zip(a.shape, a.chunks)) for a in self.arrays)

    @property
    def largest_chunk_bytes(self):
        """Uncompressed bytes of the largest chunk of any array (0 for a store without arrays)."""
        return int(max((math.prod(a.chunks) * np.dtype(a.dtype).itemsize for a in self.arrays), default=0))

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
                                   fill_value=spec.fill_value, **({} if spec.compressed else {"compressors": None}))
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

def chunk_keys(arr, region):
    """Chunk keys (``c/i/j/...``) covered by ``region`` (a tuple of slices, chunk-aligned)."""
    ranges = []
    for sl, n, c in zip(_full_region(arr, region), arr.shape, arr.chunks):
        start, stop = sl.start, sl.stop
        if start % c or (stop % c and stop != n):
            raise ValueError(f"region {region} of {arr.path} is not aligned to chunks {arr.chunks}")
        ranges.append(range(start // c, -(-stop // c)))
    if not ranges:
        return ["c"]
    grid = np.stack(np.meshgrid(*ranges, indexing="ij"), -1).reshape(-1, len(ranges))
    return ["c/" + "/".join(map(str, idx)) for idx in grid]


def _full_region(arr, region):
    region = tuple(region) + (slice(None),) * (arr.ndim - len(region))
    return [slice(*s.indices(n)[:2]) for s, n in zip(region, arr.shape)]


def checksum(data):
    """64-bit XXH3 of a bytes-like object: cheap next to the work that wrote it (rate: docs/performance.md)."""
    return xxhash.xxh3_64_intdigest(data)


def file_checksum(path):
    """:func:`checksum` of a file's bytes."""
    with open(path, "rb") as fh:
        return checksum(fh.read())


class ChunkLedger:
    """Writes chunk-aligned regions and records ``{relative path: [size, xxh3]}`` of each chunk.

    Parameters
    ----------
    root : path of the run directory (recorded paths are relative to it).
    """

    def __init__(self, root):
        self.root = Path(root)
        self.entries = {}
        self.seconds = 0.0  # spent on checksums (reported per task: the bookkeeping's cost)
        self.guard_seconds = 0.0  # spent checking outputs for NaN/inf

    def write(self, group, name, region, data, arr=None):
        """Write ``data`` to ``group[name][region]`` (``arr``: that array, when already looked up)."""
        arr = group[name] if arr is None else arr
        before = getattr(arr.store, "seconds", 0.0)
        arr[tuple(region) if len(region) else ...] = data
        self.seconds += getattr(arr.store, "seconds", 0.0) - before  # checksums computed as the bytes passed
        self.record(arr, region)

    def write_all(self, group, name, data):
        self.write(group, name, (slice(None),) * group[name].ndim, data)

    def record(self, arr, region):
        """Record the chunks of ``arr[region]``: from the bytes a :class:`CheckedStore` wrote, else
        by reading the files back."""
        t0 = time.perf_counter()
        base = Path(arr.store.root) / arr.path
        written = getattr(arr.store, "written", {})
        for key in chunk_keys(arr, region):
            p = base / key
            rel = str(p.relative_to(self.root))
            if not p.exists():
                raise DamagedStoreError(f"{p}: chunk missing right after it was written (is the run "
                                        "directory on a filesystem every worker shares?)")
            self.entries[rel] = written[rel] if rel in written else [p.stat().st_size, file_checksum(p)]
        self.seconds += time.perf_counter() - t0

    def record_file(self, path):
        """A plain output file (a FITS map, a PNG)."""
        p = Path(path)
        self.entries[str(p.relative_to(self.root))] = [p.stat().st_size, file_checksum(p)]


class CheckedStore(LocalStore):
    """A zarr LocalStore that checksums chunk bytes as they pass: no file is read twice.

    ``set`` records ``[size, xxh3]`` of every chunk it writes (``written``, keyed by the
    chunk's path relative to ``run_root``); ``get`` checks every chunk it reads against
    ``expected`` (a producer's records) and raises :class:`DamagedStoreError` for a chunk that
    is missing, has no record, or differs. Metadata (``zarr.json``) passes unchecked.
    """

    def __init__(self, root, *, read_only=False, run_root=None, expected=None, producer=None):
        super().__init__(root, read_only=read_only)
        self.run_root = Path(run_root) if run_root is not None else Path(root).parent
        self.prefix = str(Path(root).relative_to(self.run_root))
        self.expected, self.producer = expected, producer
        self.written = {}
        self.seconds = 0.0

    def with_read_only(self, read_only=False):
        out = type(self)(self.root, read_only=read_only, run_root=self.run_root, expected=self.expected,
                         producer=self.producer)
        out.written = self.written
        return out

    async def set(self, key, value):
        if _is_chunk(key):
            t0 = time.perf_counter()
            data = value.as_numpy_array()  # a view: no copy of the encoded bytes
            self.written[f"{self.prefix}/{key}"] = [int(data.nbytes), checksum(data)]
            self.seconds += time.perf_counter() - t0
        return await super().set(key, value)

    async def get(self, key, prototype=None, byte_range=None):
        buf = await super().get(key, prototype, byte_range)
        if self.expected is None or not _is_chunk(key) or byte_range is not None:
            return buf
        t0 = time.perf_counter()
        rel = f"{self.prefix}/{key}"
        fix = (f"Fix: `mmflow verify {self.run_root}` lists every damaged chunk; rerun `mmflow run ... --force` "
               "to recompute them")
        if rel not in self.expected:
            raise DamagedStoreError(f"{self.run_root / rel}: no completion record from stage '{self.producer}' "
                                    f"for this chunk. {fix}")
        if buf is None:
            raise DamagedStoreError(f"stage '{self.producer}' output is damaged: {self.run_root / rel}: missing. {fix}")
        data = buf.as_numpy_array()
        size, crc = self.expected[rel]
        if data.nbytes != size:
            raise DamagedStoreError(f"stage '{self.producer}' output is damaged: {self.run_root / rel}: "
                                    f"{data.nbytes} bytes, {size} were written. {fix}")
        if checksum(data) != crc:
            raise DamagedStoreError(f"stage '{self.producer}' output is damaged: {self.run_root / rel}: contents "
                                    f"changed (XXH3 checksum differs). {fix}")
        self.seconds += time.perf_counter() - t0
        return buf


def _is_chunk(key):
    """A chunk key of zarr v3's default encoding (``<array>/c/i/j``); metadata keys are not."""
    return key.startswith("c/") or "/c/" in key or key.endswith("/c") or key == "c"


def open_checked(run_root, store, mode="r", expected=None, producer=None):
    """Open ``run_root/store`` through a :class:`CheckedStore`."""
    path = Path(run_root) / store
    return zarr.open_group(store=CheckedStore(path, read_only=mode == "r", run_root=run_root, expected=expected,
                                              producer=producer), mode=mode)


def verify_chunks(root, entries, full=True):
    """Problems (list of strings) with the recorded chunk files: missing, truncated, changed."""
    problems = []
    for rel, (size, crc) in entries.items():
        p = Path(root) / rel
        if not p.exists():
            problems.append(f"{p}: missing")
        elif p.stat().st_size != size:
            problems.append(f"{p}: {p.stat().st_size} bytes, {size} were written")
        elif full and file_checksum(p) != crc:
            problems.append(f"{p}: contents changed (XXH3 checksum differs)")
    return problems


def dir_size(path):
    total = 0
    for dirpath, _, files in os.walk(path):
        total += sum(os.path.getsize(os.path.join(dirpath, f)) for f in files)
    return total
