"""The CLEAN part of the ``products`` stage: restored, residual, model and noise maps, PSF
stamps and the Table-1 row of one channel (docs/clean.md).

Everything is read from ``clean.zarr`` (and the splits of ``alm.zarr``) and drawn in
``products.frame``: alm are rotated (:func:`mmflow.imaging.maps.alm_to_output_map`), the
components are moved and their restoring beams turned (:func:`mmflow.imaging.clean.restore_map`
with ``to_frame``), so no map is resampled. Maps in ``products.unit``, never-seen sky UNSEEN.

=================================  =============================================================
file (``maps/``)                   content
=================================  =============================================================
``restored_<tag>.fits/.png``       residual + components convolved with the fitted beam of their
                                   declination (high-pass: ``(1 - H) dirty + H (...)``)
``residual_<tag>.fits/.png``       the restored map without the restored components
``model_<tag>.fits/.png``          the components, flux / pixel solid angle (integral = flux)
``noise_<tag>.fits/.png``          a jackknife noise realisation, ``(odd - even) / 2``, else
                                   ``sqrt(f_0 / (1 - f_0)) (day0 - all)``: its rms is the Table-1 noise
``daynight_<tag>.fits/.png``       the day/night systematics map ``sqrt(f_d f_n) (day - night)``
                                   (splits day and night; a systematics check, not noise: noise
                                   alone gives it the full map's sigma for any shares f_d, f_n)
``psf_<tag>_dec+45.fits``          PSF stamps at dec 0, +45, +75 (of date, peak 1, ARC projection)
``psf_<tag>.png``                  the three stamps
=================================  =============================================================
"""
from __future__ import annotations

import healpy
import numpy as np

from mmflow.analysis import table1
from mmflow.conventions import m_blocks
from mmflow.imaging import clean as ck
from mmflow.imaging import psf
from mmflow.imaging.jackknife import beam_noise, day_night_difference, masked_rms, noise_realisation
from mmflow.io.export import psf_stamp_header, write_healpix_fits, write_image_fits, write_mollweide_png, write_psf_png
from mmflow.io.plots import write_clean_history_png
from mmflow.io.run_stores import STORES, CLEAN_STOPS, NOISE_FIELDS
from mmflow.sky import units
from mmflow.sky.diffuse import alm_to_map
from mmflow.sky.frames import rotate_alm, rotation_matrix
from mmflow.sky.harmonics import synthesize_at
from mmflow.workflow.engine import clean_state as cs
from mmflow.workflow.engine.geometry import mmax_of, split_fractions

STAMP_DECS = table1.TABLE1_DECS_DEG
STAMP_PIXELS = 65


def _rotate_to(frame, epoch):
    return None if frame == "date" else rotation_matrix("date", frame, epoch)


def psf_stamp(cols, lmax, dec_rad, half_width_rad, n=STAMP_PIXELS):
    """``image[y, x]`` of a PSF column (source at RA 0, ``dec``), azimuthal-equidistant, x east
    to the left, normalised to the PSF at its source; returns ``(image, peak)``."""
    center = psf.table_vectors([dec_rad])[0]
    g = np.linspace(-half_width_rad, half_width_rad, n)
    yy, xx = np.meshgrid(g, -g, indexing="ij")  # column i: east offset decreasing (RA to the left)
    vals = synthesize_at(cols, psf.from_tangent(xx.ravel(), yy.ravel(), center).reshape(-1, 3), lmax)
    peak = psf.value_at(cols, lmax, center)
    return vals.reshape(n, n) / peak, peak


def clean_products(ctx, fi, tag, freq, epoch, nside, mask, meta, png):
    """Write one channel's CLEAN maps and PSF stamps; return the summary info (paths, cycle
    history, PSF FWHMs, noise, Table-1 row)."""
    cfg = ctx.cfg
    p, lmax, mmax = cfg.products, cfg.mmode.lmax, mmax_of(cfg)
    blocks = m_blocks(mmax, cfg.transfer.m_block)
    g = ctx.open(STORES.clean)
    maps_dir = ctx.run.path / "maps"
    rot = _rotate_to(p.frame, epoch)
    state, reason = cs.clean_result(g, fi, cs.clean_options(cfg.clean), int(g[STORES.clean.n_cycles][fi]))
    state.residual_alm = cs.residual_alm(g, fi, state.cycle, lmax, blocks)
    tables = [psf.table_from_array(g[STORES.clean.psf_table][fi, k]) for k in (0, 1)]
    alms = cs.split_alm(ctx, fi, lmax, mmax)
    w = cs.highpass(cfg)

    def in_frame(alm):
        return alm if rot is None else rotate_alm(alm, rot, lmax)

    resid = state.residual_alm if w is None else psf.apply_l_weights(alms["full"], lmax, 1.0 - w) + state.residual_alm
    resid_map = alm_to_map(in_frame(resid), nside, lmax)
    if w is None:
        restored = ck.restore_map(resid_map, state.comp_vec, state.comp_flux, tables[1], to_frame=rot)
    else:
        comps = ck.restore_map(np.zeros(len(resid_map)), state.comp_vec, state.comp_flux, tables[1], to_frame=rot)
        restored = ck.combine_highpass(in_frame(alms["full"]), in_frame(state.residual_alm), comps, w, lmax)
    products = {"restored": restored, "residual": resid_map,
                "model": ck.model_map(state.comp_vec, state.comp_flux, nside, rot)}
    jk = cs.jackknife_splits(ctx, fi)
    if jk[0] is not None:
        products["noise"] = alm_to_map(in_frame(noise_realisation(alms, jk[0], jk[2])), nside, lmax)
    if {"day", "night"} <= set(cfg.mmode.splits):
        products["daynight"] = alm_to_map(in_frame(day_night_alm(ctx, fi, alms)), nside, lmax)
    info = {"images": {}}
    for name, hmap in products.items():
        hmap = np.asarray(units.convert(hmap, "Jy/sr", p.unit, freq))
        ctx.check_finite(f"maps/{name} of channel {fi}", hmap)
        path = maps_dir / f"{name}_{tag}.fits"
        write_healpix_fits(path, hmap, {**meta, "CLEANCYC": state.cycle, "CONTENT": name}, mask=mask)
        ctx.ledger.record_file(path)
        entry = {"fits": f"maps/{name}_{tag}.fits", "rms_observed": float(hmap[mask].std()),
                 "max_observed": float(hmap[mask].max())}
        if png:
            write_mollweide_png(maps_dir / f"{name}_{tag}.png", hmap, f"mmflow CLEAN {name} {tag} ({p.frame}, "
                                f"{p.unit})", p.unit, mask=mask, lmax=lmax, eps=cfg.imaging.eps, freq_hz=freq,
                                frame=p.frame)
            ctx.ledger.record_file(maps_dir / f"{name}_{tag}.png")
            entry["png"] = f"maps/{name}_{tag}.png"
        info["images"][name] = entry
    info["psf_stamps"] = _write_stamps(ctx, g, fi, tag, freq, tables[0], lmax, blocks, png, psf_stamp_header,
                                       write_image_fits, write_psf_png)
    noise = dict(zip(NOISE_FIELDS, (float(x) for x in g[STORES.clean.noise][fi])))
    noise["kelvin_map_units"] = p.unit
    noise["estimator"] = jk[0]
    noise["by_split"] = split_noise(ctx, fi, alms, freq, tables[0])
    per_cycle = [int(np.count_nonzero(state.comp_cycle == c)) for c in range(state.cycle)]
    thr = float(g[STORES.clean.threshold][fi])
    info.update({
        "clean": {"cycles": state.cycle, "stop": reason, "components": int(len(state.comp_flux)),
                  "total_flux_jy": float(state.comp_flux.sum()), "threshold_jy_per_sr": thr,
                  "threshold_" + p.unit.replace("/", "_per_"): float(units.convert(thr, "Jy/sr", p.unit, freq)),
                  "highpass_lmin": cfg.clean.highpass_lmin, "history": {
                      "peak_jy_per_sr": [float(x) for x in state.peaks], "components": per_cycle}},
        "psf": _psf_summary(tables[0]), "noise": noise})
    info["clean"]["stop_code"] = CLEAN_STOPS.index(reason) if reason else -1
    return info


def day_night_alm(ctx, fi, alms):
    """The day/night systematics map's alm ``sqrt(f_d f_n) (day - night)`` of channel ``fi``, the shares
    from ``mmodes.zarr`` (:func:`mmflow.imaging.jackknife.day_night_difference`)."""
    f = split_fractions(ctx, fi)
    return day_night_difference(alms["day"], alms["night"], f["day"], f["night"])


def split_noise(ctx, fi, alms, freq, table):
    """Every jackknife the splits allow, on the clean stage's pixels and mask (frame of date):
    ``{"even_odd": ..., "per_day": ...}`` with :func:`mmflow.imaging.jackknife.beam_noise`'s
    fields, and ``"day_night"``: the rms of the day/night systematics map ``sqrt(f_d f_n) (day - night)``
    (:func:`day_night_alm`; not a noise estimate: noise alone gives it the full map's sigma)."""
    cfg = ctx.cfg
    lmax, nside = cfg.mmode.lmax, cs.clean_nside(cfg)
    lat = np.deg2rad(float(ctx.vis_attrs()["lat_deg"]))
    mask = ck.observed_mask(nside, ck.never_seen_dec_min(lat))
    out = {}
    for kind in ("even_odd", "per_day"):
        jk = cs.jackknife_splits(ctx, fi, kind)
        if jk[0] is not None:
            out[kind] = beam_noise(cs.jackknife_sigma(alms, jk, lmax, nside, mask), freq, table)
    if {"day", "night"} <= set(alms):
        diff = healpy.alm2map(day_night_alm(ctx, fi, alms), nside, lmax=lmax)
        out["day_night"] = beam_noise(masked_rms(diff, mask), freq, table)
    return out


def _psf_summary(table):
    """FWHM (arcmin) and position angle (deg) of the PSF main lobe at Table 1's declinations."""
    out = []
    for d in STAMP_DECS:
        dec = np.deg2rad(d)
        out.append({"dec_deg": d, "major_arcmin": float(np.rad2deg(psf.interp_table(table, dec, "major")) * 60),
                    "minor_arcmin": float(np.rad2deg(psf.interp_table(table, dec, "minor")) * 60),
                    "pa_deg": float(np.rad2deg(psf.interp_table(table, dec, "pa"))),
                    "peak_jy_per_sr_per_jy": float(psf.interp_table(table, dec, "peak"))})
    return out


def _write_stamps(ctx, g, fi, tag, freq, table, lmax, blocks, png, header, write_fits, write_png):
    cols = cs.psf_alm_columns(g, fi, lmax, blocks)
    decs = table["dec"]
    out, images, titles, widths = [], [], [], []
    for d in STAMP_DECS:
        k = int(np.argmin(np.abs(decs - np.deg2rad(d))))
        fwhm = table["major"][k] if np.isfinite(table["major"][k]) else np.pi / lmax
        hw = 3.0 * fwhm
        img, peak = psf_stamp(cols[:, k], lmax, decs[k], hw)
        ctx.check_finite(f"PSF stamp at dec {d:+.0f}", img)
        name = f"psf_{tag}_dec{d:+03.0f}.fits"
        write_fits(ctx.run.path / "maps" / name, img, header(
            np.rad2deg(decs[k]), np.rad2deg(2 * hw / (STAMP_PIXELS - 1)), STAMP_PIXELS,
            {"FREQ": freq, "PEAK": peak, "BMAJ": float(np.rad2deg(table["major"][k])),
             "BMIN": float(np.rad2deg(table["minor"][k])), "BPA": float(np.rad2deg(table["pa"][k])),
             "FRAME": "date", "BUNIT": "PSF/peak"}))
        ctx.ledger.record_file(ctx.run.path / "maps" / name)
        out.append({"dec_deg": d, "fits": f"maps/{name}"})
        images.append(img)
        titles.append(f"dec {d:+.0f}: {np.rad2deg(table['major'][k]) * 60:.1f}' x "
                      f"{np.rad2deg(table['minor'][k]) * 60:.1f}', PA {np.rad2deg(table['pa'][k]):.0f} deg")
        widths.append(np.rad2deg(hw))
    if png:
        path = ctx.run.path / "maps" / f"psf_{tag}.png"
        write_png(path, images, titles, widths, caption=f"{freq / 1e6:.3f} MHz PSF (frame of date, RA 0); contours "
                  "at half power and zero")
        ctx.ledger.record_file(path)
        for o in out:
            o["png"] = f"maps/psf_{tag}.png"
    return out


def table1_row(ctx, fi, freq, info):
    """Table 1's row of one channel from the CLEAN products' info and ``alm.zarr``."""
    cfg = ctx.cfg
    g = ctx.open(STORES.clean)
    lmax, mmax = cfg.mmode.lmax, mmax_of(cfg)
    frac = ctx.read(STORES.alm.fraction_above, (slice(fi, fi + 1),))[0][: mmax + 1]
    n_m = lmax - np.arange(mmax + 1) + 1  # each m's Gram size: the fraction over every singular value
    width = float(ctx.vis_attrs().get("channel_width_hz", 0.0))
    noise = {"kelvin": info["noise"]["kelvin"], "mjy_per_beam": info["noise"]["mjy_per_beam"]}
    return table1.table1_row(freq, width, psf.table_from_array(g[STORES.clean.psf_table][fi, 0]), noise,
                             float(np.sum(frac * n_m) / np.sum(n_m)), info["noise"].get("by_split"))


def clean_history_figure(ctx, parts, tags):
    """``maps/clean_history.png``: every channel's residual peak and components per cycle."""
    hist, thr = {}, {}
    for tag, part in zip(tags, parts):
        h = part["clean"]["history"]
        hist[tag] = [{"peak": pk, "components": n} for pk, n in zip(h["peak_jy_per_sr"], h["components"])]
        if part["clean"]["threshold_jy_per_sr"] > 0:
            thr[tag] = part["clean"]["threshold_jy_per_sr"]
    path = ctx.run.path / "maps" / "clean_history.png"
    write_clean_history_png(path, hist, thr, unit="Jy/sr")
    ctx.ledger.record_file(path)
    return "maps/clean_history.png"
