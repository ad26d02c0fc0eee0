"""The science part of the ``products`` stage: flux scale, astrometric registration (per
channel) and the spectral-index products (across channels) (docs/products.md).

Per channel (:func:`channel_science`), for the catalogue sources the array sees:

* the PSF of each source, ``a_PSF = (G + eps I)^-1 G conj(Y_lm(r_s))`` per m block with the
  data's filters, through the CLEAN stage's stored Cholesky factors when it kept them, else
  factorised from ``normal.zarr``'s Grams (:func:`psf_at`); its main lobe fitted
  (:func:`mmflow.imaging.psf.measure_psf`) gives the source's FWHM;
* the flux density ``S = [sum_disc I - n median_annulus I] / [same for the PSF]``, the PSF
  evaluated at the disc's and annulus's pixels only (:func:`mmflow.analysis.fluxscale.alm_sampler`)
  (:func:`mmflow.analysis.fluxscale.source_flux`) on the channel's (dirty, Tikhonov) map, with
  a disc of ``products.flux_disc_fwhm`` and an annulus of ``products.flux_annulus_fwhm`` FWHMs.
  With CLEAN, ``clean_jy`` is also given: the CLEAN components' flux within the disc.
  Without CLEAN the flux scale is measured the same way (the PSF needs only the Grams). With
  even and odd splits, ``measured_err_jy`` is the rms change of the measured flux when noise
  realisations are added to the map (:func:`mmflow.analysis.fluxscale.flux_deviations`): the
  jackknife noise map ``(odd - even) / 2``, its negative, and both turned about the pole of date
  by multiples of ``2 pi / NOISE_ROTATIONS``;
* peeled or subtracted sources (``peel.zarr``), which are no longer in the map: their flux is
  the published flux times the per-integration factor of the peel solutions
  (:func:`mmflow.analysis.fluxscale.peel_flux_factors`), median over integrations;
* with ``products.astrometry``, the registration of the map against those sources
  (:func:`mmflow.analysis.astrometry.register`), positions before and after the fitted rotation.

Across channels (:func:`finalize_science`): ``maps/fluxscale.{csv,json,png}``, and with >= 2
channels the T-T spectral index between the lowest and highest channel
(``maps/spectral_index_{beta,r2}.fits``, ``maps/spectral_index.png``), with >= 3 the
three-colour Mollweide of the lowest, middle and highest (``maps/three_colour.png``).
"""
from __future__ import annotations

import csv
import io
import json

import healpy
import numpy as np

from mmflow.analysis.astrometry import register, registration_rows
from mmflow.analysis.fluxscale import (alm_sampler, disc_minus_annulus, flux_deviations, flux_row, peel_flux_factors,
                                       source_flux)
from mmflow.analysis.spectral_index import local_tt
from mmflow.conventions import m_block_slice, m_blocks, m_slice, n_alm
from mmflow.imaging import psf
from mmflow.imaging.clean import never_seen_dec_min
from mmflow.imaging.jackknife import noise_realisation
from mmflow.io.export import write_healpix_fits
from mmflow.io.plots import write_flux_scale_png, write_spectral_index_png, write_three_colour_png
from mmflow.sky import units
from mmflow.sky.frames import rotation_matrix
from mmflow.sky.sources import CATALOG, epoch_year, get_sources
from mmflow.workflow.engine import clean_state as cs
from mmflow.workflow.engine.clean_state import jackknife_splits, split_alm
from mmflow.workflow.engine.geometry import mmax_of
from mmflow.io.run_stores import STORES

NOISE_ROTATIONS = 8  # noise realisations for the flux errors: 2 x this (turned jackknife maps and negatives)
FLUX_COLUMNS = ("name", "freq_hz", "measured_jy", "measured_err_jy", "model_jy", "ratio", "clean_jy", "method",
                "fwhm_arcmin", "reference")


def seen_sources(names, icrs_to_date, dec_min_rad, exclude=()):
    """The catalogue sources (``names``; None: all) north of ``dec_min`` (frame of date), less ``exclude``."""
    srcs = get_sources(list(CATALOG) if names is None else names)
    return [s for s in srcs if s.name not in exclude and (icrs_to_date @ s.vector_icrs())[2] > np.sin(dec_min_rad)]


def psf_at(ctx, fi, vecs_date):
    """PSF alm columns ``(n_alm, n_src)`` (frame of date, Jy/sr per Jy) of sources at ``vecs_date``,
    one m block at a time (one block's operators in memory)."""
    cfg = ctx.cfg
    lmax = cfg.mmode.lmax
    stored = cfg.clean.enabled and cfg.clean.keep_factors
    out = np.zeros((n_alm(lmax), len(vecs_date)), np.complex128)
    for m0, m1 in m_blocks(mmax_of(cfg), cfg.transfer.m_block):
        ops = cs.stored_operators(ctx, fi, m0, m1) if stored else cs.block_operators_from_gram(ctx, fi, m0, m1)
        out[m_block_slice(lmax, m0, m1)] = psf.psf_columns(ops, lmax, vecs_date, m0, m1)
    return out


def _peel_rows(ctx, fi, freq, epoch_year, wanted):
    """Flux rows of the sources ``peel.zarr`` removed (peeled or subtracted), from the peel solutions;
    the modelled sources (``peel.model_sources``) stay in the data and are measured in the map."""
    g = ctx.open(STORES.peel)
    kept = set(g.attrs.get("modelled", []))
    index = {n: s for s, n in enumerate(g.attrs["sources"]) if n not in kept}  # store column of each
    names = list(index)
    mode = ctx.read(STORES.peel.mode, (slice(None), slice(fi, fi + 1)))[:, 0]  # (time, src, pol)
    scale = ctx.read(STORES.peel.scale, (slice(None), slice(fi, fi + 1)))[:, 0]
    gains = ctx.read(STORES.peel.dd_gains, (slice(None), slice(fi, fi + 1)))[:, 0]  # (time, src, ant, pol)
    rows = []
    for src in get_sources(names):
        if wanted is not None and src.name not in wanted:
            continue
        s = index[src.name]
        fac = np.stack([peel_flux_factors(mode[:, s, p], scale[:, s, p], gains[:, s, :, p])
                        for p in range(mode.shape[-1])], axis=-1)
        n = np.isfinite(fac).sum(-1)  # the mean over the polarisations that were fitted
        fac = np.where(n > 0, np.where(np.isfinite(fac), fac, 0.0).sum(-1) / np.maximum(n, 1), np.nan)
        good = np.isfinite(fac)
        if not good.any():
            continue
        model = float(src.flux(freq, epoch_year))
        mad = np.median(np.abs(fac[good] - np.median(fac[good])))
        err = float(1.4826 * mad / np.sqrt(good.sum())) * model  # robust: a few wild low-elevation fits
        rows.append(flux_row(src, float(np.median(fac[good])) * model, freq, epoch_year, measured_err_jy=err,
                             method=f"peel ({int(good.sum())} integrations)"))
    return rows, names


def channel_science(ctx, fi, tag, freq, epoch, hmap, nside):
    """Flux scale and astrometry of one channel; returns the summary info to merge."""
    cfg = ctx.cfg
    p, lmax = cfg.products, cfg.mmode.lmax
    if not (p.flux_scale or p.astrometry):
        return {}
    year = epoch_year(epoch)
    icrs_to_date = rotation_matrix("icrs", "date", epoch)
    # the map was drawn from the frame of date with rotation_matrix("date", frame): its inverse
    # (the transpose) and the same path for the sources keep everything on the map's own frame
    date_to_map = rotation_matrix("date", p.frame, epoch)
    to_map = date_to_map @ icrs_to_date
    peel_rows, peeled = _peel_rows(ctx, fi, freq, year, p.flux_scale_sources) if cfg.peel.enabled else ([], [])
    dec_min = never_seen_dec_min(np.deg2rad(float(ctx.vis_attrs()["lat_deg"])))
    srcs = seen_sources(p.flux_scale_sources, icrs_to_date, dec_min, exclude=peeled)
    out = {}
    if not srcs:
        out["flux_scale"] = peel_rows
        return out
    v_date = np.array([icrs_to_date @ s.vector_icrs() for s in srcs])
    cols = psf_at(ctx, fi, v_date)
    fwhm = np.array([np.sqrt(f["major"] * f["minor"]) for f in (psf.measure_psf(cols[:, k], lmax, v_date[k])
                                                                 for k in range(len(srcs)))])
    comps = _clean_components(ctx, fi) if cfg.clean.enabled else None
    if p.flux_scale:
        a0, a1 = p.flux_annulus_fwhm
        vecs = [to_map @ src.vector_icrs() for src in srcs]
        radii, annuli = p.flux_disc_fwhm * fwhm, [(a0 * f, a1 * f) for f in fwhm]
        map_to_date = date_to_map.T
        scale = float(units.convert(1.0, "Jy/sr", p.unit, freq))  # the PSF's Jy/sr per Jy in the map's unit
        psf_sums, rows = [], []
        for k, src in enumerate(srcs):
            pmap = alm_sampler(cols[:, k], lmax, nside, map_to_date, scale)
            psf_sums.append(disc_minus_annulus(pmap, vecs[k], radii[k], annuli[k], nside))
            extra = {"method": "map", "fwhm_arcmin": float(np.rad2deg(fwhm[k]) * 60)}
            if comps is not None:
                near = np.arccos(np.clip(comps[0] @ v_date[k], -1, 1)) < radii[k]
                extra["clean_jy"] = float(comps[1][near].sum())
            rows.append(flux_row(src, source_flux(hmap, pmap, vecs[k], radii[k], annuli[k]), freq, year, **extra))
        dev = [flux_deviations(hmap, alm_sampler(a, lmax, nside, map_to_date, scale), vecs, radii, annuli, psf_sums)
               for a in _noise_alms(ctx, fi)]
        if dev:
            for row, err in zip(rows, np.sqrt(np.mean(np.square(dev), axis=0))):
                row["measured_err_jy"] = float(err)
        out["flux_scale"] = rows + peel_rows
    if p.astrometry:
        fw = float(np.median(fwhm))
        res = register(hmap, srcs, fw, 0.6 * fw, axis="z" if p.astrometry_axis == "z" else None,
                       rotation=to_map)
        rows, fit = registration_rows(res)
        out["astrometry"] = {"rows": [{"freq_hz": float(freq), **r} for r in rows],
                             "fit": {**fit, "fwhm_arcmin": fw * 60 * 180 / np.pi}}
    return out


def _noise_alms(ctx, fi, n_rot=NOISE_ROTATIONS):
    """Noise realisations (alm, frame of date, Jy/sr): the jackknife's
    (:func:`mmflow.imaging.jackknife.noise_realisation`: ``(odd - even) / 2``, else from a
    ``day<k>`` split), its negative, and the same turned about the pole of date by
    ``2 pi k / n_rot`` (``a_lm exp(-i m dphi)``: the noise of a drift scan depends on
    declination); none without even and odd or day<k> splits."""
    cfg = ctx.cfg
    kind, _, fractions = jackknife_splits(ctx, fi)
    if kind is None:
        return
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    noise = noise_realisation(split_alm(ctx, fi, lmax, mmax), kind, fractions)
    for k in range(n_rot):
        turned = noise.copy()
        for m in range(mmax + 1):
            turned[m_slice(lmax, m)] *= np.exp(-2j * np.pi * m * k / n_rot)
        yield turned
        yield -turned


def _clean_components(ctx, fi):
    """CLEAN's components of one channel (frame of date): ``(vecs, fluxes)``."""
    g = ctx.open(STORES.clean)
    state, _ = cs.clean_result(g, fi, cs.clean_options(ctx.cfg.clean), int(g[STORES.clean.n_cycles][fi]))
    return state.comp_vec, state.comp_flux


# ----------------------------------------------------------------------------- across channels

def flux_csv(rows):
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(FLUX_COLUMNS), extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def finalize_science(ctx, parts, tags):
    """Flux-scale table and figure, spectral index and three-colour products; returns the
    summary entries (paths relative to the run) and records every file written."""
    cfg = ctx.cfg
    p = cfg.products
    maps = ctx.run.path / "maps"
    out = {}

    def record(name):
        ctx.ledger.record_file(maps / name)
        return f"maps/{name}"

    rows = [r for part in parts for r in part.get("flux_scale", [])]
    if p.flux_scale and rows:
        (maps / "fluxscale.json").write_text(json.dumps(rows, indent=1))
        (maps / "fluxscale.csv").write_text(flux_csv(rows))
        out["flux_scale"] = {"rows": rows, "files": {"JSON": record("fluxscale.json"), "CSV": record("fluxscale.csv")}}
        if p.png:
            drawn = write_flux_scale_png(maps / "fluxscale.png", rows, epoch_year(parts[0]["epoch_jd"]))
            out["flux_scale"]["figure"] = record("fluxscale.png")
            out["flux_scale"]["median_ratio"] = drawn["median_ratio"]
    astro = [part["astrometry"] for part in parts if "astrometry" in part]
    if astro:
        out["astrometry"] = {"rows": [r for a in astro for r in a["rows"]],
                             "fit": {tag: part["astrometry"]["fit"] for tag, part in zip(tags, parts)
                                     if "astrometry" in part}}
    if p.spectral_index and len(parts) >= 2:
        out["spectral_index"] = _spectral(ctx, parts, maps, record)
    return out


def _kelvin_map(ctx, part):
    """The channel's map to compare across channels (restored with CLEAN, else the Tikhonov
    map) in K, and its seen pixels."""
    rel = part["images"]["restored"]["fits"] if "images" in part else part["fits"]
    m = healpy.read_map(str(ctx.run.path / rel))
    seen = m != healpy.UNSEEN
    m = np.where(seen, np.asarray(units.convert(np.where(seen, m, 0.0), part["unit"], "K", part["freq_hz"])), 0.0)
    return m, seen


def _spectral(ctx, parts, maps, record):
    """T-T beta and R^2 between the lowest and highest channel; three colours with >= 3."""
    p = ctx.cfg.products
    order = np.argsort([q["freq_hz"] for q in parts])
    lo, hi = parts[order[0]], parts[order[-1]]
    work = 2 * p.spectral_index_nside
    degraded = []
    for part in (lo, hi):
        m, seen = _kelvin_map(ctx, part)
        m = np.where(seen, m, healpy.UNSEEN)
        d = healpy.ud_grade(m, work) if healpy.npix2nside(len(m)) != work else m
        degraded.append(d)
    use = (degraded[0] != healpy.UNSEEN) & (degraded[1] != healpy.UNSEEN)
    tt = local_tt(degraded[0], degraded[1], lo["freq_hz"], hi["freq_hz"], p.spectral_index_radius_deg,
                  nside_out=p.spectral_index_nside, mask=use)
    out = {"freqs_hz": [lo["freq_hz"], hi["freq_hz"]], "radius_deg": p.spectral_index_radius_deg,
           "input": "restored" if "images" in lo else "map", "files": {}}
    meta = {"FREQ1": lo["freq_hz"], "FREQ2": hi["freq_hz"], "RADIUS": p.spectral_index_radius_deg,
            "COORDSYS": {"icrs": "C", "galactic": "G", "date": "C"}[p.frame]}
    for name in ("beta", "r2"):
        vals = tt[name]
        write_healpix_fits(maps / f"spectral_index_{name}.fits", np.where(np.isfinite(vals), vals, healpy.UNSEEN),
                           {**meta, "CONTENT": name, "BUNIT": ""}, mask=np.isfinite(vals))
        out["files"][f"{name} (FITS)"] = record(f"spectral_index_{name}.fits")
    good = np.isfinite(tt["beta"]) & (tt["r2"] > 0.9)
    out["beta_median_r2_above_0.9"] = float(np.median(tt["beta"][good])) if good.any() else None
    out["fraction_r2_above_0.9"] = float(good.mean())
    if p.png:
        write_spectral_index_png(maps / "spectral_index.png", tt["beta"], tt["r2"], lo["freq_hz"], hi["freq_hz"],
                                 frame=p.frame)
        out["figures"] = [{"path": record("spectral_index.png"),
                           "caption": f"T-T spectral index and R^2, {lo['freq_hz'] / 1e6:.3f} to "
                                      f"{hi['freq_hz'] / 1e6:.3f} MHz ({p.spectral_index_radius_deg:g} deg regions)"}]
        if len(parts) >= 3:
            three = [parts[order[0]], parts[order[len(order) // 2]], parts[order[-1]]]
            ms = [_kelvin_map(ctx, q) for q in three]
            seen = ms[0][1] & ms[1][1] & ms[2][1]
            write_three_colour_png(maps / "three_colour.png", [m for m, _ in ms], [q["freq_hz"] for q in three],
                                   mask=seen, frame=p.frame)
            out["figures"].append({"path": record("three_colour.png"), "caption": "three channels scaled by nu^2.5 "
                                   "(red: lowest frequency; white: T ~ nu^-2.5)"})
    return out
