"""Tasks of one channel read and correct that channel only (issue 21: a task bounded by its chunk).

``vis.zarr`` holds one channel per chunk, and :func:`mmflow.workflow.engine.blocks.read_block` reads a
range of channels and applies every correction (calibrate, peel, terrestrial) with the solutions of
those channels. Checked on the calibration demo's chain with two channels: a one-channel block
equals that channel of the whole block, bit for bit, through every correction; the terrestrial
stage runs a task per channel and time chunk (both phases) and the peel, calibrate and terrestrial
tasks each read one channel.
"""
import numpy as np
import pytest
import zarr

from mmflow.workflow.engine import blocks
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.context import Context
from mmflow.io.run_stores import STORES
from mmflow.workflow.pipeline import PIPELINE
from mmflow.workflow.engine.runner import run_workflow

CHAIN = ["observation.freqs_mhz=[40.0, 47.0]", "observation.integration_s=269.2627828",  # 320: two time chunks
         "telescope.radius_m=18", "mmode.lmax=20", "cluster.kind=synchronous",
         "mmode.baseline_chunk=48",  # 120 baselines in three chunks (the grouped read's test)
         "calibrate.solint_s=3600"]  # hourly solutions: the demo's 600 s make six times the calibrate tasks
UPTO = ("simulate", "calibrate", "peel", "terrestrial")


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    d = tmp_path_factory.mktemp("channels")
    cfg = load_config("workflows/demo-calibrate.yaml", CHAIN + [f"run.directory={d}"])
    seen = []
    real = blocks.read_block

    def spy(ctx, rows=slice(None), columns=slice(None), cross=False, channels=slice(None)):
        seen.append((ctx.stage.name, channels))
        return real(ctx, rows, columns, cross, channels)

    mp = pytest.MonkeyPatch()
    for mod in ("calibrate", "peel", "terrestrial"):
        mp.setattr(f"mmflow.workflow.stages.{mod}.stage.read_block", spy)
    try:
        run_workflow(cfg, only=UPTO, progress=False, log=lambda *a: None)
    finally:
        mp.undo()
    return cfg, d, seen


def test_every_task_of_the_chain_reads_one_channel(chain):
    cfg, d, seen = chain
    by_stage = {}
    for stage, channels in seen:
        by_stage.setdefault(stage, []).append(channels)
    assert set(by_stage) == {"calibrate", "peel", "terrestrial"}
    for stage, chans in by_stage.items():
        assert all(c.stop - c.start == 1 for c in chans), (stage, chans)
        assert {c.start for c in chans} == {0, 1}, stage
    # terrestrial: sums and amplitudes per channel and time chunk; peel per channel and time chunk
    assert len(by_stage["terrestrial"]) == 2 * 2 * 2 and len(by_stage["peel"]) == 2 * 2


def test_a_channels_block_equals_that_channel_of_the_whole_block_through_every_correction(chain):
    cfg, d, _ = chain
    ctx = Context(cfg.model_dump_json(), str(d)).for_stage(PIPELINE.stage("mmodes"))
    assert [s.name for s in ctx.corrections()] == ["calibrate", "peel", "terrestrial"]
    rows = slice(200, 300)  # across the two time chunks
    whole = blocks.read_block(ctx, rows, slice(10, 90))
    assert np.abs(whole.vis).max() > 0 and whole.vis.shape[2] == 2
    for fi in (0, 1):
        one = blocks.read_block(ctx, rows, slice(10, 90), channels=slice(fi, fi + 1))
        assert one.channel_indices() == [(0, fi)]
        np.testing.assert_array_equal(one.vis[:, :, 0], whole.vis[:, :, fi])
        np.testing.assert_array_equal(one.weights[:, :, 0], whole.weights[:, :, fi])
        np.testing.assert_array_equal(one.autos[:, :, 0], whole.autos[:, :, fi])
    # the channels' gains differ (the simulated bandpass): a one-channel block corrected with the
    # solutions at its index on the block's axis (0) instead of its channel's would not pass above
    gains = zarr.open_group(str(d / "gains.zarr"), mode="r")["gains"][:]
    assert np.abs(gains[:, 0] - gains[:, 1]).max() > 1e-3 * np.abs(gains).max()
    with pytest.raises(ValueError, match="contiguous"):
        blocks.read_block(ctx, rows, channels=slice(0, 2, 2))


def test_a_block_read_in_groups_of_baseline_chunks_equals_one_read(chain, monkeypatch):
    """:func:`blocks.read_columns` with groups of one baseline chunk (``READ_DECODE_BYTES`` below a chunk) gives
    the values of one read of the region, across time chunks and from a column inside a chunk; and the groups
    are whole chunks: no read spans a chunk boundary of the grid."""
    cfg, d, _ = chain
    ctx = Context(cfg.model_dump_json(), str(d)).for_stage(PIPELINE.stage("mmodes")).for_task(keep_handles=True)
    arr = zarr.open_group(str(d / "vis.zarr"), mode="r")["vis"]
    cb = arr.chunks[1]
    assert arr.shape[1] > 2 * cb, "the test needs a block over three baseline chunks"
    region = (slice(200, 300), slice(cb // 2, arr.shape[1]), slice(0, 2))
    whole = blocks.read_columns(ctx, STORES.vis.vis, region, np.complex128)
    np.testing.assert_array_equal(whole, arr[200:300, cb // 2:, 0:2].astype(np.complex128))
    reads = []
    real = ctx.read
    monkeypatch.setattr(blocks, "READ_DECODE_BYTES", 1.0)
    object.__setattr__(ctx, "read", lambda array, region=(): reads.append(region[1]) or real(array, region))
    grouped = blocks.read_columns(ctx, STORES.vis.vis, region, np.complex128)
    assert grouped.tobytes() == whole.tobytes()
    assert len(reads) == -(-arr.shape[1] // cb) and reads[0] == slice(cb // 2, cb)
    assert all(s.start % cb == 0 and (s.stop % cb == 0 or s.stop == arr.shape[1]) for s in reads[1:])
