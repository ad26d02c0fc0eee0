"""The ``mmodes`` stage: corner turn (time -> baseline), corrections on read, m-mode transform.

Each task reads every integration of one baseline chunk from ``vis.zarr`` (whole chunks,
checked against the data stage's records), applies the corrections of the enabled
solve-then-apply stages (gains, peeled sources, terrestrial templates: never written back),
bins onto sidereal bins, transforms each data split and writes ``mmodes.zarr``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmflow.io.run_stores import mmodes_store
from mmflow.mmode.noise import difference_variance, mmode_inverse_variance, radiometer_variance
from mmflow.mmode.transform import sidereal_bins, split_mmode_transform
from mmflow.workflow.context import SIDEREAL_DAY_S, _parse
from mmflow.workflow.stages.base import Stage, all_stages, register

CORRECTION_STORES = ("gains.zarr", "peel.zarr", "terrestrial.zarr")


def mmax_of(cfg):
    return cfg.mmode.mmax if cfg.mmode.mmax is not None else cfg.mmode.lmax


def n_bins_of(cfg, integration_s):
    return cfg.mmode.n_bins or int(round(SIDEREAL_DAY_S / integration_s))


@dataclass
class DataBlock:
    """What a corner-turn task holds: all integrations of one baseline chunk (corrected in place)."""

    vis: np.ndarray  # (time, baseline, freq) complex128
    weights: np.ndarray  # (time, baseline, freq)
    pairs: np.ndarray  # (baseline, 2) antenna indices
    columns: slice  # the chunk's baselines in vis.zarr
    autos: np.ndarray  # (time, antenna, freq) |V_ii|


def corrections(cfg):
    """The enabled solve-then-apply stages, in pipeline order."""
    return [s for s in all_stages() if s.kind == "solve" and s.enabled(cfg) and s.apply is not None]


def _prepare(ctx):
    cfg = ctx.cfg
    vis = ctx.open("vis.zarr")
    nt, nbl, nf = vis["vis"].shape
    mmax, n_bins = mmax_of(cfg), n_bins_of(cfg, vis.attrs["integration_s"])
    splits = list(cfg.mmode.splits)
    ctx.create(mmodes_store(len(splits), nf, mmax, nbl, vis["vis"].chunks[1],
                            {"mmax": mmax, "n_bins": n_bins, "splits": splits}))
    return [f"b{i:05d}" for i in range(-(-nbl // vis["vis"].chunks[1]))]


def _task(ctx, key):
    cfg = ctx.cfg
    vg = ctx.open("vis.zarr")
    nt, nbl, nf = vg["vis"].shape
    ch = vg["vis"].chunks[1]
    i = int(key[1:])
    cols = slice(i * ch, min(nbl, (i + 1) * ch))
    block = DataBlock(ctx.read("vis.zarr", "vis", (slice(None), cols)).astype(np.complex128),
                      ctx.read("vis.zarr", "weights", (slice(None), cols)).astype(float),
                      vg["pairs"][cols], cols, ctx.read("vis.zarr", "autos"))
    for stage in corrections(_parse(ctx.config_json)):
        stage.apply(ctx, block)
    lst = ctx.read("vis.zarr", "lst")
    good_t = np.isfinite(lst)
    vis, w, lst = block.vis[good_t], block.weights[good_t], lst[good_t]
    g = ctx.open("mmodes.zarr", mode="r+")
    mmax, n_bins, splits = g.attrs["mmax"], g.attrs["n_bins"], g.attrs["splits"]
    out = np.zeros((len(splits), nf, mmax + 1, 2, vis.shape[1]), np.complex128)
    inv_var = np.zeros((nf, vis.shape[1]))
    sigma2 = None
    if cfg.mmode.noise == "radiometer":
        mean = np.nanmean(block.autos[good_t], axis=0)  # (antenna, freq)
        have = {a: mean[a] for a in range(len(mean)) if np.all(np.isfinite(mean[a]))}
        sigma2 = radiometer_variance(have, block.pairs, vg.attrs["channel_width_hz"], vg.attrs["integration_s"],
                                     str(ctx.run.store("vis.zarr")))
    for fi in range(nf):
        binned, wsum, offset = sidereal_bins(lst, vis[:, :, fi], (w[:, :, fi] > 0).astype(float), n_bins,
                                             cfg.mmode.min_coverage, source=str(ctx.run.store("vis.zarr")))
        out[:, fi] = split_mmode_transform(binned, mmax, offset, splits)
        s2 = sigma2[fi] if sigma2 is not None else difference_variance(vis[:, :, fi], w[:, :, fi])
        inv_var[fi] = mmode_inverse_variance(s2, wsum)
    ctx.write(g, "mmodes", (slice(None), slice(None), slice(None), slice(None), cols), out)
    ctx.write(g, "inv_var", (slice(None), cols), inv_var)
    return {"baselines": int(vis.shape[1])}


register(Stage("mmodes", ("mmode",), ("vis.zarr",) + CORRECTION_STORES, ("mmodes.zarr",), _prepare, _task,
               description="corrections on read, sidereal binning + m-mode transform per baseline chunk"))
