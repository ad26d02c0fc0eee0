"""A store's declared file count and largest chunk against what zarr really writes."""
import os

import numpy as np

from mmflow.io.stores import ArraySpec, StoreSpec


def _files_on_disk(root):
    return sum(len(files) for _, _, files in os.walk(root))


def test_n_files_counts_what_zarr_writes_with_every_chunk_written(tmp_path):
    # uneven chunkings: edges that do not divide, an axis chunked whole, a scalar-like array
    spec = StoreSpec("x.zarr", (
        ArraySpec("a", ("t", "b"), (10, 7), (4, 3), "complex64"),
        ArraySpec("b", ("t",), (5,), (5,), "float64"),
        ArraySpec("c", ("t", "b", "p"), (3, 2, 9), (1, 2, 4), "int32"),
    ))
    g = spec.create(tmp_path)
    for a in spec.arrays:
        g[a.name][...] = np.ones(a.shape, a.dtype)
    assert spec.n_files == _files_on_disk(tmp_path / "x.zarr") == 1 + (1 + 3 * 3) + (1 + 1) + (1 + 3 * 1 * 3)
    assert spec.largest_chunk_bytes == 4 * 3 * 8


def test_an_unwritten_store_holds_fewer_files_than_its_bound(tmp_path):
    spec = StoreSpec("y.zarr", (ArraySpec("a", ("t",), (100,), (10,), "float32"),))
    spec.create(tmp_path)
    assert _files_on_disk(tmp_path / "y.zarr") == 2 < spec.n_files == 12
