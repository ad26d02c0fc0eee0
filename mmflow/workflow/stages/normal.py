"""``transfer`` and ``normal`` stages: streaming normal equations, reduced per m block.

``transfer``: one task per (frequency, baseline group). A group is a run of baseline chunks
(sorted by per-baseline lmax); the task streams over its chunks computing ``B_m`` for every
m and accumulating ``G_m = B^H N^-1 B``, ``r_m = B^H N^-1 v`` and ``v^H N^-1 v`` in memory
(B is never stored unless ``transfer.mode=store``); it writes its partial sums to
``partials.zarr`` at its own group index.
``normal``: one task per (frequency, m block) sums the partials over groups in a fixed
order (bit-identical on re-runs) into ``normal.zarr``.
"""
from __future__ import annotations

import numpy as np
import zarr

from mmflow.mmode.engine import GridCache, chunk_blocks, plan_chunks
from mmflow.mmode.normal import NormalAccumulator
from mmflow.workflow.stages.base import Stage, register
from mmflow.workflow.stages.mmodes import mmax_of


def _groups(ctx, fi):
    cfg = ctx.cfg
    tel = ctx.telescope()
    chunks, lmax_b = plan_chunks(tel, tel.freqs_hz[fi], cfg.mmode.lmax, cfg.transfer.baseline_chunk,
                                 cfg.transfer.per_baseline_lmax)
    n_groups = max(1, min(len(chunks), n_groups_of(ctx)))
    # contiguous runs of chunks with balanced cost (~ lmax_b^3 each)
    cost = np.cumsum([len(c.index) * float(c.lmax) ** 3 for c in chunks])
    cut = np.searchsorted(cost, cost[-1] * np.arange(1, n_groups) / n_groups)
    bounds = np.concatenate([[0], cut, [len(chunks)]])
    groups = [chunks[bounds[k]:bounds[k + 1]] for k in range(n_groups) if bounds[k + 1] > bounds[k]]
    return groups, lmax_b


def relative_weights(inv_var):
    """Noise weights scaled to unit mean over measured baselines.

    Minimum-variance weighting changes the relative weights of baselines, not the scale of
    ``B^H B``: eps keeps the meaning it has for unweighted data (the paper's eps = 0.01).
    """
    inv_var = np.asarray(inv_var, float)
    good = inv_var > 0
    return inv_var / inv_var[good].mean() if good.any() else inv_var


def n_groups_of(ctx):
    """Reduction groups: enough to keep every worker busy, few enough to keep partials small."""
    c = ctx.cfg.cluster
    return max(2, 2 * c.n_workers * c.threads_per_worker)


def _transfer_prepare(ctx):
    cfg = ctx.cfg
    tel = ctx.telescope()
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    tel.check_lmax(lmax)
    g = zarr.open_group(str(ctx.run.store("partials.zarr")), mode="a")
    keys = []
    for fi in range(len(tel.freqs_hz)):
        groups, _ = _groups(ctx, fi)
        fg = g.require_group(f"f{fi}")
        ng = len(groups)
        if "rhs" not in fg:
            for m in range(mmax + 1):
                n = lmax - m + 1
                fg.create_array(f"gram_m{m:05d}", shape=(ng, n, n), chunks=(1, n, n), dtype="complex128", fill_value=0)
            fg.create_array("rhs", shape=(ng, mmax + 1, lmax + 1), chunks=(1, mmax + 1, lmax + 1),
                            dtype="complex128", fill_value=0)
            fg.create_array("vhv", shape=(ng, mmax + 1), chunks=(1, mmax + 1), dtype="float64", fill_value=0)
        keys += [f"f{fi}-g{k:04d}" for k in range(ng)]
    if cfg.transfer.mode == "store":
        _create_transfer_store(ctx, tel, lmax, mmax)
    return keys


def _create_transfer_store(ctx, tel, lmax, mmax):
    g = zarr.open_group(str(ctx.run.store("transfer.zarr")), mode="a")
    nbl = len(tel.antenna_pairs())
    dt = "complex64" if ctx.cfg.transfer.dtype == "float32" else "complex128"
    for fi in range(len(tel.freqs_hz)):
        fg = g.require_group(f"f{fi}")
        if "order" in fg:
            continue
        chunks, _ = plan_chunks(tel, tel.freqs_hz[fi], lmax, ctx.cfg.transfer.baseline_chunk,
                                ctx.cfg.transfer.per_baseline_lmax)
        fg.create_array("order", data=np.concatenate([c.index for c in chunks]).astype("int64"))
        for m in range(mmax + 1):
            fg.create_array(f"B_m{m:05d}", shape=(2, nbl, lmax - m + 1),
                            chunks=(2, ctx.cfg.transfer.baseline_chunk, lmax - m + 1), dtype=dt, fill_value=0)


def _transfer_task(ctx, key):
    cfg = ctx.cfg
    fi, gk = (int(x[1:]) for x in key.split("-"))
    tel = ctx.telescope()
    f = tel.freqs_hz[fi]
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    groups, lmax_b = _groups(ctx, fi)
    mg = zarr.open_group(str(ctx.run.store("mmodes.zarr")), mode="r")
    mm_all = mg["mmodes"]
    inv_var = relative_weights(mg["inv_var"][fi]) if cfg.transfer.noise_weighting else np.ones(mg["inv_var"].shape[1])
    dtype = np.float32 if cfg.transfer.dtype == "float32" else np.float64
    # accumulators follow the transfer precision: complex64 halves the ~lmax^3/3 Gram memory
    acc = NormalAccumulator(lmax, mmax, np.complex64 if dtype == np.float32 else np.complex128)
    cache = GridCache(tel, f)
    store = zarr.open_group(str(ctx.run.store("transfer.zarr")), mode="r+") if cfg.transfer.mode == "store" else None
    chunk_pos = sum(len(gr) for gr in groups[:gk])
    n_bl = 0
    for ci, chunk in enumerate(groups[gk]):
        idx = chunk.index
        order = np.argsort(idx)
        mm = np.empty((mmax + 1, 2, len(idx)), np.complex128)
        mm[..., order] = mm_all.get_orthogonal_selection((fi, slice(None), slice(None), idx[order]))
        for m, blk in chunk_blocks(tel, f, chunk, lmax, lmax_b, dtype, cache, mmax, pad=store is not None):
            acc.add_mmodes(m, blk, mm, inv_var[idx])
            if store is not None:
                rows = slice((chunk_pos + ci) * cfg.transfer.baseline_chunk,
                             (chunk_pos + ci) * cfg.transfer.baseline_chunk + len(idx))
                b2 = np.zeros((2, len(idx), lmax - m + 1), blk.dtype)
                b2[0] = blk[:len(idx)]
                if m > 0:
                    b2[1] = blk[len(idx):]
                store[f"f{fi}/B_m{m:05d}"][:, rows, :] = b2
        n_bl += len(idx)
    pg = zarr.open_group(str(ctx.run.store(f"partials.zarr/f{fi}")), mode="r+")
    rhs = np.zeros((mmax + 1, lmax + 1), np.complex128)
    for m in range(mmax + 1):
        pg[f"gram_m{m:05d}"][gk] = acc.gram[m]
        rhs[m, m:] = acc.rhs[m]
    pg["rhs"][gk] = rhs
    pg["vhv"][gk] = acc.vhv
    return {"baselines": n_bl}


register(Stage("transfer", ("mmode", "transfer", "beam"), ("mmodes",), ("partials.zarr", "transfer.zarr"),
               _transfer_prepare, _transfer_task,
               description="transfer blocks + herk into partial normal equations per baseline group"))


def _m_blocks(cfg):
    mb = cfg.transfer.m_block
    mmax = mmax_of(cfg)
    return [(m0, min(mmax + 1, m0 + mb)) for m0 in range(0, mmax + 1, mb)]


def _normal_prepare(ctx):
    cfg = ctx.cfg
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    nf = len(ctx.telescope().freqs_hz)
    g = zarr.open_group(str(ctx.run.store("normal.zarr")), mode="a")
    if "rhs" not in g:
        mb = cfg.transfer.m_block
        g.create_array("rhs", shape=(nf, mmax + 1, lmax + 1), chunks=(1, mb, lmax + 1), dtype="complex128", fill_value=0)
        g.create_array("vhv", shape=(nf, mmax + 1), chunks=(1, mb), dtype="float64", fill_value=0)
        for fi in range(nf):
            for m in range(mmax + 1):
                n = lmax - m + 1
                g.create_array(f"f{fi}/gram_m{m:05d}", shape=(n, n), chunks=(n, n), dtype="complex128", fill_value=0)
    return [f"f{fi}-m{m0:05d}" for fi in range(nf) for m0, _ in _m_blocks(cfg)]


def _normal_task(ctx, key):
    fi, m0 = (int(x[1:]) for x in key.split("-"))
    cfg = ctx.cfg
    m1 = dict(_m_blocks(cfg))[m0]
    pg = zarr.open_group(str(ctx.run.store(f"partials.zarr/f{fi}")), mode="r")
    g = zarr.open_group(str(ctx.run.store("normal.zarr")), mode="r+")
    ng = pg["rhs"].shape[0]
    for m in range(m0, m1):
        arr = pg[f"gram_m{m:05d}"]
        g[f"f{fi}/gram_m{m:05d}"][:] = _ordered_sum(arr[k] for k in range(ng))
    g["rhs"][fi, m0:m1] = _ordered_sum(pg["rhs"][:, m0:m1, :])
    g["vhv"][fi, m0:m1] = _ordered_sum(pg["vhv"][:, m0:m1])
    return {"m": [m0, m1]}


def _ordered_sum(parts):
    """Sum over groups in a fixed order (floating-point sums are then bit-identical on re-runs)."""
    it = iter(parts)
    total = np.array(next(it), copy=True)
    for p in it:
        total = total + p
    return total


register(Stage("normal", ("transfer",), ("transfer",), ("normal.zarr",), _normal_prepare, _normal_task,
               description="sum partial normal equations over baseline groups, per m block"))
