"""``solve`` (per frequency and m block) and ``products`` (per frequency) stages.

``alm.zarr``: ``alm`` (frequency, m, l) complex128 in Jy/sr, frame of date, zero for l < m;
``lcurve`` (frequency, m, 200, 2) with ``||a||^2`` and ``||v - Ba||^2`` per trial eps;
``fraction_above`` (frequency, m): fraction of singular values above sqrt(eps).
Products: ``maps/map_<MHz>MHz.fits`` (HEALPix, RING, in ``products.frame``/``products.unit``),
a Mollweide PNG, ``maps/lcurve_<MHz>MHz.png`` and ``maps/summary.json``.
"""
from __future__ import annotations

import json

import numpy as np
import zarr

from mmflow.conventions import m_slice, n_alm
from mmflow.imaging.filters import filter_mask
from mmflow.imaging.lcurve import default_eps_grid, lcurve_block, lcurve_corner
from mmflow.imaging.solvers import singular_fraction_above, solve_block
from mmflow.mmode.normal import hermitian_full
from mmflow.workflow.stages.base import Stage, register
from mmflow.workflow.stages.mmodes import mmax_of
from mmflow.workflow.stages.normal import _m_blocks

N_EPS = 200


def _solve_prepare(ctx):
    cfg = ctx.cfg
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    nf = len(ctx.telescope().freqs_hz)
    g = zarr.open_group(str(ctx.run.store("alm.zarr")), mode="a")
    mb = cfg.transfer.m_block
    if "alm" not in g:
        g.create_array("alm", shape=(nf, mmax + 1, lmax + 1), chunks=(1, mb, lmax + 1), dtype="complex128", fill_value=0)
        g.create_array("lcurve", shape=(nf, mmax + 1, N_EPS, 2), chunks=(1, mb, N_EPS, 2), dtype="float64", fill_value=0)
        g.create_array("fraction_above", shape=(nf, mmax + 1), chunks=(1, mb), dtype="float64", fill_value=0)
        g.create_array("eps_grid", data=default_eps_grid(N_EPS))
    return [f"f{fi}-m{m0:05d}" for fi in range(nf) for m0, _ in _m_blocks(cfg)]


def _prior_alm(cfg, fi, lmax):
    if cfg.imaging.method != "prior":
        return None
    import healpy

    from mmflow.sky.diffuse import map_to_alm
    from mmflow.sky.frames import rotate_alm, rotation_matrix

    hmap = healpy.read_map(cfg.imaging.prior_map)
    return rotate_alm(map_to_alm(hmap, lmax), rotation_matrix(cfg.products.frame, "date", cfg.observation.epoch_jd), lmax)


def _solve_task(ctx, key):
    cfg = ctx.cfg
    im = cfg.imaging
    fi, m0 = (int(x[1:]) for x in key.split("-"))
    m1 = dict(_m_blocks(cfg))[m0]
    lmax = cfg.mmode.lmax
    ng = zarr.open_group(str(ctx.run.store("normal.zarr")), mode="r")
    rhs_all, vhv_all = ng["rhs"][fi, m0:m1], ng["vhv"][fi, m0:m1]
    prior = _prior_alm(cfg, fi, lmax)
    eps_grid = default_eps_grid(N_EPS)
    alm = np.zeros((m1 - m0, lmax + 1), np.complex128)
    lc = np.zeros((m1 - m0, N_EPS, 2))
    frac = np.zeros(m1 - m0)
    filt = dict(zero_monopole=im.zero_monopole, filter_m0=im.filter_m0, filter_m1_lmin=im.filter_m1_lmin)
    for m in range(m0, m1):
        gram = hermitian_full(ng[f"f{fi}/gram_m{m:05d}"][:])
        rhs = rhs_all[m - m0, m:]
        keep = filter_mask(m, lmax, **filt)
        # one eigendecomposition serves the fraction and the L-curve when nothing is filtered
        eig = np.linalg.eigh(gram) if im.lcurve and keep.all() else None
        frac[m - m0] = singular_fraction_above(gram, im.eps, None if eig is None else eig[0])
        if not keep.any():
            continue
        g, r = gram[np.ix_(keep, keep)], rhs[keep]
        p = None if prior is None else prior[m_slice(lmax, m)][keep]
        sol = solve_block(im.method, g, r, im.eps, ell=np.arange(m, lmax + 1)[keep], a_prior=p)
        alm[m - m0, m:][keep] = sol
        if im.lcurve:
            lc[m - m0, :, 0], lc[m - m0, :, 1] = lcurve_block(g, r, vhv_all[m - m0], eps_grid, eig)
    out = zarr.open_group(str(ctx.run.store("alm.zarr")), mode="r+")
    out["alm"][fi, m0:m1] = alm
    out["lcurve"][fi, m0:m1] = lc
    out["fraction_above"][fi, m0:m1] = frac
    return {"m": [m0, m1]}


register(Stage("solve", ("imaging",), ("normal",), ("alm.zarr",), _solve_prepare, _solve_task,
               description="Tikhonov (or alternative) solve + L-curve per m block"))


def healpy_alm(alm_ml, lmax, mmax):
    """(m, l) padded array -> healpy-layout vector."""
    out = np.zeros(n_alm(lmax), np.complex128)
    for m in range(mmax + 1):
        out[m_slice(lmax, m)] = alm_ml[m, m:]
    return out


def _products_prepare(ctx):
    (ctx.run.path / "maps").mkdir(parents=True, exist_ok=True)
    return [f"f{fi}" for fi in range(len(ctx.telescope().freqs_hz))]


def _products_task(ctx, key):
    from mmflow.imaging.maps import alm_to_output_map, default_nside
    from mmflow.io.export import write_healpix_fits, write_lcurve_png, write_mollweide_png

    cfg = ctx.cfg
    fi = int(key[1:])
    tel = ctx.telescope()
    f = float(tel.freqs_hz[fi])
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    ag = zarr.open_group(str(ctx.run.store("alm.zarr")), mode="r")
    alm = healpy_alm(ag["alm"][fi], lmax, mmax)
    p = cfg.products
    nside = p.nside or 2 * default_nside(lmax)
    hmap = alm_to_output_map(alm, lmax, f, cfg.observation.epoch_jd, p.frame, p.unit, nside)
    tag = f"{f / 1e6:.3f}MHz"
    maps = ctx.run.path / "maps"
    meta = {"FREQ": f, "LMAX": lmax, "EPS": cfg.imaging.eps, "METHOD": cfg.imaging.method, "BUNIT": p.unit,
            "COORDSYS": {"icrs": "C", "galactic": "G", "date": "C"}[p.frame], "EPOCHJD": cfg.observation.epoch_jd}
    write_healpix_fits(maps / f"map_{tag}.fits", hmap, meta)
    lc = ag["lcurve"][fi].sum(axis=0)
    eps = ag["eps_grid"][:]
    info = {"freq_hz": f, "fits": f"maps/map_{tag}.fits", "nside": nside, "unit": p.unit, "frame": p.frame,
            "map_min": float(np.min(hmap)), "map_max": float(np.max(hmap)), "map_rms": float(np.std(hmap)),
            "fraction_singular_values_above_sqrt_eps": float(np.mean(ag["fraction_above"][fi])),
            "lcurve_corner_eps": lcurve_corner(lc[:, 0], lc[:, 1], eps) if lc.any() else None}
    if p.png:
        write_mollweide_png(maps / f"map_{tag}.png", hmap, f"mmflow {tag} ({p.frame}, {p.unit})", p.unit)
        if lc.any():
            write_lcurve_png(maps / f"lcurve_{tag}.png", lc, eps, cfg.imaging.eps)
        info["png"] = f"maps/map_{tag}.png"
    (maps / f"summary_{tag}.json").write_text(json.dumps(info, indent=2))
    return info


def _products_finalize(ctx):
    maps = ctx.run.path / "maps"
    parts = [json.loads(p.read_text()) for p in sorted(maps.glob("summary_*MHz.json"))]
    (maps / "summary.json").write_text(json.dumps({"maps": parts}, indent=2))
    return {"maps": len(parts)}


register(Stage("products", ("products",), ("solve",), ("maps",), _products_prepare, _products_task,
               _products_finalize, description="HEALPix FITS maps, Mollweide PNGs, L-curves, summary"))
