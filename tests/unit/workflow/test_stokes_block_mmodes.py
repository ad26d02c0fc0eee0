"""The stokes stage's block task reads its m-modes one store chunk at a time and holds them in the transfer's
precision (``stages/stokes/stage._block_mmodes``): the values of the block's region of the store, for the kept
baselines in their order, cast; the bytes it holds are what the blocks of m are sized by
(``blocks.mmode_bytes_per_m``)."""
import numpy as np
import pytest
import zarr

from mmflow.io.run_stores import STORES
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.stages.stokes.blocks import mmode_bytes_per_m
from mmflow.workflow.stages.stokes.stage import _block_mmodes


class _Ctx:
    """The two context calls the reader makes, over one in-memory zarr array chunked by baselines as
    ``mmodes.zarr`` is; counts the chunks each read touches."""

    def __init__(self, arr):
        self.arr, self.reads = arr, []

    def open(self, store):
        assert store == STORES.mmodes
        return {STORES.mmodes.mmodes_corr: self.arr}

    def read(self, handle, region):
        assert handle == STORES.mmodes.mmodes_corr
        self.reads.append(region[-1])
        return self.arr[region]


@pytest.mark.parametrize("dtype", [np.complex64, np.complex128])
def test_block_mmodes_are_the_stores_region_for_the_kept_baselines_cast(dtype):
    rng = np.random.default_rng(3)
    shape = (3, 2, 21, 2, 4, 23)  # split, freq, m, pm, corr, baseline
    data = rng.normal(size=shape) + 1j * rng.normal(size=shape)
    arr = zarr.create_array(store=zarr.storage.MemoryStore(), shape=shape, chunks=shape[:5] + (5,), dtype="complex128")
    arr[...] = data
    keep = np.array([0, 2, 3, 9, 10, 11, 17, 22])  # chunks 0, 1, 2, 3, 4; chunk 1 (5-9) only baseline 9
    ctx = _Ctx(arr)
    got = _block_mmodes(ctx, 1, (4, 13), keep, dtype)
    assert got.dtype == dtype and got.shape == (3, 9, 2, 4, len(keep))
    np.testing.assert_array_equal(got, data[:, 1, 4:13][..., keep].astype(dtype))
    assert len(ctx.reads) == 5  # each store chunk with a kept baseline read once
    ctx.reads.clear()
    _block_mmodes(ctx, 0, (0, 21), np.array([5, 6]), dtype)
    assert ctx.reads == [slice(5, 10)]  # chunks without kept baselines are not read


def test_a_block_holds_its_mmodes_at_the_transfers_precision(tmp_path):
    """Three splits x four correlations x +-m x baselines, 8 bytes each for ``transfer.dtype: float32``, 16 for
    float64: what :func:`_block_mmodes` allocates."""
    for dt, size in (("float32", 8), ("float64", 16)):
        cfg = load_config("workflows/demo.yaml", [f"transfer.dtype={dt}", f"run.directory={tmp_path}"])
        assert mmode_bytes_per_m(cfg, 3, 100) == 3 * 2 * 4 * 100 * size
