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
    block = DataBlock(ctx.read(STORES.vis.vis, region).astype(np.complex128),
                      ctx.read(STORES.vis.weights, region).astype(float),
                      vg[STORES.vis.pairs][columns], rows, columns,
                      ctx.read(STORES.vis.autos, (rows, slice(None), channels)),
                      ctx.read(STORES.vis.lst, (rows,)), channels=channels)
    if cross:
        block.cross = ctx.read(STORES.vis.vis_cross, region).astype(np.complex128)
        block.cross_weights = ctx.read(STORES.vis.weights_cross, region).astype(float)
    for stage in ctx.corrections():
        stage.apply(ctx, block)
    return block
