"""``solve`` (per frequency and m block) and ``products`` (per frequency) stages.

``solve`` calls :func:`mmflow.imaging.solvers.solve_m` (the engine's own per-m loop) on the
reduced normal equations and writes ``alm.zarr``: ``alm`` per data split in Jy/sr in the frame
of date, ``lcurve`` (first split) and ``fraction_above``. ``products`` rotates to
``products.frame`` at the *data's* epoch (stored with the visibilities) and writes
``maps/map_<MHz>MHz.fits``, PNGs and summaries; only the files it lists are ever removed.
"""
from __future__ import annotations

import json

import numpy as np

from mmflow.conventions import m_slice, n_alm
from mmflow.imaging.lcurve import default_eps_grid, lcurve_corner
from mmflow.imaging.solvers import solve_m
from mmflow.io.run_stores import alm_store, gram_name, m_blocks
from mmflow.mmode.normal import hermitian_full
from mmflow.workflow.stages.base import Stage, register
from mmflow.workflow.stages.mmodes import mmax_of

N_EPS = 200
SOLVE_CONFIG = ("mmode.lmax", "mmode.mmax", "transfer.m_block", "imaging", "products.frame")


def _solve_prepare(ctx):
    cfg = ctx.cfg
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    ng = ctx.open("normal.zarr")
    n_split, nf = ng["rhs"].shape[:2]
    ctx.create(alm_store(nf, lmax, mmax, cfg.transfer.m_block, n_split, default_eps_grid(N_EPS)))
    return [f"f{fi}-m{m0:05d}" for fi in range(nf) for m0, _ in m_blocks(mmax, cfg.transfer.m_block)]


def _prior_alm(ctx, lmax):
    """The prior map (``imaging.prior_map``, in ``products.frame``) as alm in the frame of date."""
    import healpy

    from mmflow.sky.diffuse import map_to_alm
    from mmflow.sky.frames import rotate_alm, rotation_matrix

    cfg = ctx.cfg
    hmap = healpy.read_map(cfg.imaging.prior_map)
    epoch = ctx.vis_attrs()["epoch_jd"]
    return rotate_alm(map_to_alm(hmap, lmax), rotation_matrix(cfg.products.frame, "date", epoch), lmax)


def _filters(im):
    return dict(zero_monopole=im.zero_monopole, filter_m0=im.filter_m0, filter_m1_lmin=im.filter_m1_lmin)


def _solve_task(ctx, key):
    cfg = ctx.cfg
    im = cfg.imaging
    fi, m0 = (int(x[1:]) for x in key.split("-"))
    m1 = dict(m_blocks(mmax_of(cfg), cfg.transfer.m_block))[m0]
    lmax = cfg.mmode.lmax
    rhs_all = ctx.read("normal.zarr", "rhs", (slice(None), slice(fi, fi + 1), slice(m0, m1)))[:, 0]
    vhv_all = ctx.read("normal.zarr", "vhv", (slice(None), slice(fi, fi + 1), slice(m0, m1)))[:, 0]
    grams = ctx.read("normal.zarr", gram_name(fi, m0))
    prior = _prior_alm(ctx, lmax) if im.method == "prior" else None
    eps_grid = default_eps_grid(N_EPS) if im.lcurve else None
    n_split = rhs_all.shape[0]
    alm = np.zeros((n_split, 1, m1 - m0, lmax + 1), np.complex128)
    lc = np.zeros((1, m1 - m0, N_EPS, 2))
    frac = np.zeros((1, m1 - m0))
    for m in range(m0, m1):
        n = lmax - m + 1
        sol = solve_m(hermitian_full(grams[m - m0, :n, :n]), rhs_all[:, m - m0, m:], m, lmax, im.method, im.eps,
                      _filters(im), None if prior is None else prior[m_slice(lmax, m)], vhv_all[0, m - m0], eps_grid)
        alm[:, 0, m - m0, m:] = sol.alm
        frac[0, m - m0] = sol.fraction_above
        if sol.lcurve is not None:
            lc[0, m - m0] = sol.lcurve
    out = ctx.open("alm.zarr", mode="r+")
    ctx.write(out, "alm", (slice(None), slice(fi, fi + 1), slice(m0, m1)), alm)
    ctx.write(out, "lcurve", (slice(fi, fi + 1), slice(m0, m1)), lc)
    ctx.write(out, "fraction_above", (slice(fi, fi + 1), slice(m0, m1)), frac)
    return {"m": [m0, m1]}


def _prior_files(cfg):
    return [cfg.imaging.prior_map] if cfg.imaging.method == "prior" and cfg.imaging.prior_map else []


register(Stage("solve", SOLVE_CONFIG, ("vis.zarr", "normal.zarr"), ("alm.zarr",), _solve_prepare, _solve_task,
               files=_prior_files, description="Tikhonov (or alternative) solve + L-curve per m block"))


def healpy_alm(alm_ml, lmax, mmax):
    """(m, l) padded array -> healpy-layout vector."""
    out = np.zeros(n_alm(lmax), np.complex128)
    for m in range(mmax + 1):
        out[m_slice(lmax, m)] = alm_ml[m, m:]
    return out


def frequency_tags(freqs_hz):
    """``'40.000MHz'``-style names, with as many decimals (>= 3) as make every channel's unique."""
    mhz = np.asarray(freqs_hz, float) / 1e6
    for decimals in range(3, 10):
        tags = [f"{f:.{decimals}f}MHz" for f in mhz]
        if len(set(tags)) == len(tags):
            return tags
    raise ValueError(f"duplicate frequencies {mhz.tolist()} MHz")


def _products_prepare(ctx):
    (ctx.run.path / "maps").mkdir(parents=True, exist_ok=True)
    return [f"f{fi}" for fi in range(ctx.open("alm.zarr")["alm"].shape[1])]


def _products_task(ctx, key):
    from mmflow.imaging.maps import alm_to_output_map, default_nside
    from mmflow.imaging.sky_mask import observed_sky_mask
    from mmflow.io.export import write_healpix_fits, write_lcurve_png, write_mollweide_png
    from mmflow.sky.frames import rotation_matrix

    cfg = ctx.cfg
    fi = int(key[1:])
    vis = ctx.open("vis.zarr")
    freqs = vis["freqs_hz"][:]
    f, epoch, lat = float(freqs[fi]), float(vis.attrs["epoch_jd"]), float(vis.attrs["lat_deg"])
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    alm = healpy_alm(ctx.read("alm.zarr", "alm", (slice(0, None), slice(fi, fi + 1)))[0, 0], lmax, mmax)
    lc = ctx.read("alm.zarr", "lcurve", (slice(fi, fi + 1),))[0].sum(axis=0)
    frac = ctx.read("alm.zarr", "fraction_above", (slice(fi, fi + 1),))[0]
    eps = ctx.read("alm.zarr", "eps_grid")
    p = cfg.products
    nside = p.nside or 2 * default_nside(lmax)
    hmap = alm_to_output_map(alm, lmax, f, epoch, p.frame, p.unit, nside)
    mask = observed_sky_mask(nside, lat, None if p.frame == "date" else rotation_matrix(p.frame, "date", epoch))
    tag = frequency_tags(freqs)[fi]
    maps = ctx.run.path / "maps"
    meta = {"FREQ": f, "LMAX": lmax, "EPS": cfg.imaging.eps, "METHOD": cfg.imaging.method, "BUNIT": p.unit,
            "COORDSYS": {"icrs": "C", "galactic": "G", "date": "C"}[p.frame], "EPOCHJD": epoch}
    write_healpix_fits(maps / f"map_{tag}.fits", hmap, meta, mask=mask)
    ctx.ledger.record_file(maps / f"map_{tag}.fits")
    seen = hmap[mask]
    info = {"freq_hz": f, "fits": f"maps/map_{tag}.fits", "nside": nside, "unit": p.unit, "frame": p.frame,
            "epoch_jd": epoch, "resolution_deg": _resolution_deg(vis, f, lmax), "sky_fraction_seen": float(mask.mean()),
            "map_min": float(seen.min()), "map_max": float(seen.max()), "map_rms": float(seen.std()),
            "fraction_singular_values_above_sqrt_eps": float(np.mean(frac)),
            "lcurve_corner_eps": lcurve_corner(lc[:, 0], lc[:, 1], eps) if lc.any() else None}
    if p.png:
        write_mollweide_png(maps / f"map_{tag}.png", hmap, f"mmflow {tag} ({p.frame}, {p.unit})", p.unit,
                            mask=mask, lmax=lmax, eps=cfg.imaging.eps, freq_hz=f,
                            resolution_deg=info["resolution_deg"], frame=p.frame)
        ctx.ledger.record_file(maps / f"map_{tag}.png")
        info["png"] = f"maps/map_{tag}.png"
        if lc.any():
            info["chosen_over_corner_eps"] = write_lcurve_png(
                maps / f"lcurve_{tag}.png", lc, eps, cfg.imaging.eps, corner=info["lcurve_corner_eps"], freq_hz=f,
                weighted=cfg.transfer.noise_weighting)
            ctx.ledger.record_file(maps / f"lcurve_{tag}.png")
    (maps / f"summary_{tag}.json").write_text(json.dumps(info, indent=2))
    ctx.ledger.record_file(maps / f"summary_{tag}.json")
    return info


def _resolution_deg(vis, freq_hz, lmax):
    """The finer of the lmax limit (180 / lmax degrees) and the longest baseline's lambda / b."""
    enu, pairs = vis["antenna_enu"][:], vis["pairs"][:]
    b_max = float(np.linalg.norm(enu[pairs[:, 1]] - enu[pairs[:, 0]], axis=1).max())
    return float(max(180.0 / lmax, np.degrees(299792458.0 / freq_hz / b_max) if b_max > 0 else 0.0))


def _products_finalize(ctx):
    maps = ctx.run.path / "maps"
    tags = frequency_tags(ctx.open("vis.zarr")["freqs_hz"][:])
    parts = [json.loads((maps / f"summary_{t}.json").read_text()) for t in tags]
    (maps / "summary.json").write_text(json.dumps({"maps": parts}, indent=2))
    ctx.ledger.record_file(maps / "summary.json")
    return {"maps": len(parts)}


register(Stage("products", ("mmode.lmax", "mmode.mmax", "imaging.eps", "imaging.method", "products",
                            "transfer.noise_weighting"),
               ("vis.zarr", "alm.zarr"), ("maps",), _products_prepare, _products_task, _products_finalize,
               description="HEALPix FITS maps, Mollweide PNGs, L-curves, summary"))
