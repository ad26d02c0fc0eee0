"""The ``mmodes`` stage: corner turn (time -> baseline) and the m-mode transform.

Each task reads all integrations of one baseline chunk from ``vis.zarr`` (whole chunks,
bounded memory), bins them onto sidereal bins, transforms, estimates the noise from
differences of successive integrations and writes ``mmodes.zarr``:
``mmodes`` (frequency, m, 2, baseline) complex128 and ``inv_var`` (frequency, baseline).
"""
from __future__ import annotations

import numpy as np
import zarr

from mmflow.mmode.transform import mmode_noise_variance, mmode_transform, sidereal_bins
from mmflow.workflow.context import SIDEREAL_DAY_S
from mmflow.workflow.stages.base import Stage, register


def mmax_of(cfg):
    return cfg.mmode.mmax if cfg.mmode.mmax is not None else cfg.mmode.lmax


def n_bins_of(cfg, integration_s):
    return cfg.mmode.n_bins or int(round(SIDEREAL_DAY_S / integration_s))


def _prepare(ctx):
    cfg = ctx.cfg
    vis = zarr.open_group(str(ctx.run.store("vis.zarr")), mode="r")
    nt, nbl, nf = vis["vis"].shape
    ch = vis["vis"].chunks[1]
    g = zarr.open_group(str(ctx.run.store("mmodes.zarr")), mode="a")
    mmax = mmax_of(cfg)
    if "mmodes" not in g:
        g.create_array("mmodes", shape=(nf, mmax + 1, 2, nbl), chunks=(nf, mmax + 1, 2, ch), dtype="complex128",
                       fill_value=0)
        g.create_array("inv_var", shape=(nf, nbl), chunks=(nf, ch), dtype="float64", fill_value=0)
        g.attrs.update({"mmax": mmax, "n_bins": n_bins_of(cfg, vis.attrs["integration_s"])})
    return [f"b{i:05d}" for i in range(-(-nbl // ch))]


def noise_variance_from_differences(vis, weights):
    """Per-sample noise variance per baseline from successive differences (sky ~constant over 2 samples).

    ``sigma^2 ~ median(|V_t+1 - V_t|^2) / (2 ln 2)`` over pairs where both samples are unflagged
    (the median of an exponential distribution is ``ln 2`` times its mean: robust to RFI spikes).
    """
    d = np.abs(np.diff(vis, axis=0)) ** 2
    ok = (weights[1:] > 0) & (weights[:-1] > 0)
    d = np.where(ok, d, np.nan)
    with np.errstate(all="ignore"):
        med = np.nanmedian(d, axis=0)
    return np.where(np.isfinite(med), med / (2 * np.log(2)), np.inf)


def noise_variance_radiometer(ctx, sl, bandwidth_hz, integration_s):
    """``sigma^2 = <V_ii> <V_jj> / (dnu tau)``, shape (frequency, baseline in ``sl``), from
    time-averaged autocorrelations (read once for every frequency)."""
    from mmflow.errors import InputError

    vg = zarr.open_group(str(ctx.run.store("vis.zarr")), mode="r")
    pairs = vg["pairs"][:]
    autos = np.flatnonzero(pairs[:, 0] == pairs[:, 1])
    if len(autos) == 0:
        raise InputError(str(ctx.run.store("vis.zarr")), "pairs", "no autocorrelations for the radiometer "
                         "equation", "set mmode.noise=data, or ingest autocorrelations")
    mean_auto = np.nanmean(np.abs(vg["vis"].get_orthogonal_selection((slice(None), autos, slice(None)))), axis=0)
    power = np.full((int(pairs.max()) + 1, mean_auto.shape[1]), np.nan)
    power[pairs[autos, 0]] = mean_auto
    p = pairs[sl]
    return (power[p[:, 0]] * power[p[:, 1]]).T / (bandwidth_hz * integration_s)


def _task(ctx, key):
    cfg = ctx.cfg
    vg = zarr.open_group(str(ctx.run.store("vis.zarr")), mode="r")
    ch = vg["vis"].chunks[1]
    i = int(key[1:])
    sl = slice(i * ch, min(vg["vis"].shape[1], (i + 1) * ch))
    vis = vg["vis"][:, sl, :].astype(np.complex128)
    w = vg["weights"][:, sl, :].astype(float)
    lst = vg["lst"][:]
    good_t = np.isfinite(lst)
    vis, w, lst = vis[good_t], w[good_t], lst[good_t]
    g = zarr.open_group(str(ctx.run.store("mmodes.zarr")), mode="r+")
    mmax, n_bins = g.attrs["mmax"], g.attrs["n_bins"]
    out = np.zeros((vis.shape[2], mmax + 1, 2, vis.shape[1]), np.complex128)
    inv_var = np.zeros((vis.shape[2], vis.shape[1]))
    radiometer = None
    if cfg.mmode.noise == "radiometer":
        radiometer = noise_variance_radiometer(ctx, sl, cfg.observation.channel_width_khz * 1e3,
                                               vg.attrs["integration_s"])
    for fi in range(vis.shape[2]):
        binned, wsum, offset = sidereal_bins(lst, vis[:, :, fi], (w[:, :, fi] > 0).astype(float), n_bins,
                                             cfg.mmode.min_coverage, source=str(ctx.run.store("vis.zarr")))
        out[fi] = mmode_transform(binned, mmax, offset)
        if radiometer is not None:
            sigma2 = np.where(np.isfinite(radiometer[fi]), radiometer[fi], np.inf)
        else:
            sigma2 = noise_variance_from_differences(vis[:, :, fi], w[:, :, fi])
        var_m = mmode_noise_variance(wsum, 1.0) * np.where(np.isfinite(sigma2), sigma2, 0)
        inv_var[fi] = np.where((var_m > 0) & np.isfinite(sigma2), 1.0 / np.where(var_m > 0, var_m, 1), 0.0)
    g["mmodes"][:, :, :, sl] = out
    g["inv_var"][:, sl] = inv_var
    return {"baselines": int(vis.shape[1])}


register(Stage("mmodes", ("mmode",), ("simulate", "ingest", "calibrate", "peel", "terrestrial"),
               ("mmodes.zarr",), _prepare, _task, description="sidereal binning + m-mode transform per baseline chunk"))
