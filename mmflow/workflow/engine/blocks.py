"""Blocks of visibilities as stage tasks read them, with the corrections of solve-then-apply stages.

A solve-then-apply stage (calibrate, peel, terrestrial) never rewrites ``vis.zarr``: each
writes a small solution store, and its ``apply(ctx, block)`` corrects a block where the data
are next read. :func:`read_block` reads any rectangle (integrations x baselines) and applies,
in pipeline order, the corrections of the enabled stages that come *before* the reader, so
the peel stage reads calibrated data, the terrestrial stage calibrated and peeled data, and
the ``mmodes`` corner turn all of them; a correction can never be applied twice.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mmflow.io.run_stores import STORES

#: decoded bytes of ``vis.zarr`` chunks one read of a block decodes at once at most: a block spanning more
#: baseline chunks than that is read in groups of whole chunks, one group after another (zarr decodes a
#: read's chunks concurrently, its whole chunks also for a few integrations of them; at 352 antennas with
#: ``mmode.baseline_chunk`` 8192 one integration's read held 7-8 decoded chunks of 16.8 MB, 0.11-0.13 GB,
#: as the reads happened to overlap)
READ_DECODE_BYTES = 32e6


@dataclass
class DataBlock:
    """Visibilities of ``rows`` x ``columns`` x ``channels`` of ``vis.zarr`` (corrected in place by ``apply``)."""

    vis: np.ndarray  # (time, baseline, freq, pol) complex128
    weights: np.ndarray  # (time, baseline, freq, pol) float
    pairs: np.ndarray  # (baseline, 2) antenna indices
    rows: slice  # the block's integrations in vis.zarr
    columns: slice  # the block's baselines in vis.zarr
    autos: np.ndarray  # (time, antenna, freq, pol) |V_ii| of the block's integrations (calibrated by apply)
    lst: np.ndarray  # (time,) rad
    cross: np.ndarray = None  # (time, baseline, freq, cross_pol) complex128: xy, yx, where read
    cross_weights: np.ndarray = None  # like cross
    channels: slice = None  # the block's channels in vis.zarr (its freq axis); None: every channel

    def channel_indices(self):
        """``(k, fi)`` for each channel of the block: its index ``k`` on the block's freq axis and ``fi``
        in ``vis.zarr`` (the index every solution store and the telescope's frequencies use)."""
        start = 0 if self.channels is None else self.channels.start
        return [(k, start + k) for k in range(self.vis.shape[2])]


def read_block(ctx, rows=slice(None), columns=slice(None), cross=False, channels=slice(None)):
    """Read a block of ``vis.zarr`` and apply, in pipeline order, the corrections of the enabled
    solve-then-apply stages before the reading stage (``ctx.corrections()``).

    ``cross``: also read the cross hands (``vis_cross``, ``weights_cross``; full-Stokes imaging);
    a correction corrects them with the same per-feed solutions. ``channels``: a contiguous range
    of channels (a task of one channel reads and corrects that channel only: ``vis.zarr`` holds one
    channel per chunk, so its memory and work do not grow with the channels of the run)."""
    vg = ctx.open(STORES.vis)
    nt, nbl, nf = vg[STORES.vis.vis].shape[:3]
    rows, columns, channels = slice(*rows.indices(nt)), slice(*columns.indices(nbl)), slice(*channels.indices(nf))
    if channels.step != 1 or channels.stop <= channels.start:
        raise ValueError(f"read_block: channels {channels} is not a contiguous, non-empty range of the {nf} channels")
    region = (rows, columns, channels)
    block = DataBlock(read_columns(ctx, STORES.vis.vis, region, np.complex128),
                      read_columns(ctx, STORES.vis.weights, region, float),
                      vg[STORES.vis.pairs][columns], rows, columns,
                      ctx.read(STORES.vis.autos, (rows, slice(None), channels)),
                      ctx.read(STORES.vis.lst, (rows,)), channels=channels)
    if cross:
        block.cross = read_columns(ctx, STORES.vis.vis_cross, region, np.complex128)
        block.cross_weights = read_columns(ctx, STORES.vis.weights_cross, region, float)
    for stage in ctx.corrections():
        stage.apply(ctx, block)
    return block


def decode_group_chunks(chunk_bytes):
    """Baseline chunks :func:`read_columns` reads at once: as many as :data:`READ_DECODE_BYTES` holds of
    ``chunk_bytes`` each (a chunk's full shape), at least one."""
    return max(1, int(READ_DECODE_BYTES // chunk_bytes))


def read_columns(ctx, array, region, dtype):
    """``array[rows, columns, channels]`` (a ``vis.zarr`` array; ``region`` of slices with step 1) as ``dtype``,
    read in groups of whole baseline chunks (:func:`decode_group_chunks`), each converted into the output as
    it arrives: the values of one read of the region, with at most a group's chunks decoded at once."""
    rows, columns, channels = region
    arr = ctx.array(ctx.open(array.store), array)
    chunk_bytes = float(np.prod(arr.chunks)) * arr.dtype.itemsize
    step = decode_group_chunks(chunk_bytes) * arr.chunks[1]
    out = np.empty((rows.stop - rows.start, columns.stop - columns.start, channels.stop - channels.start)
                   + arr.shape[3:], dtype)
    c0 = columns.start
    while c0 < columns.stop:
        c1 = min(columns.stop, (c0 // step + 1) * step)  # to the group's end on the chunk grid
        out[:, c0 - columns.start:c1 - columns.start] = ctx.read(array, (rows, slice(c0, c1), channels))
        c0 = c1
    return out
