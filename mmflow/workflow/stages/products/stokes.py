"""The full-Stokes part of the ``products`` stage (``imaging.stokes: [I, Q, U, V]``; docs/stokes.md).

=================================  =============================================================
file (``maps/``)                   content
=================================  =============================================================
``stokes_<tag>.fits``              I, Q, U, V (columns ``I_STOKES`` .. ``V_STOKES``) of the
                                   full-Stokes solve, IAU convention (``POLCCONV = 'IAU'``: Q > 0
                                   north-south, angle from north through east in
                                   ``products.frame``), ``products.unit``
``stokes_noise_<tag>.fits``        a jackknife noise realisation of I, Q, U, V (``(odd - even) / 2``,
                                   else of the first day; ``mmode.splits``), whose rms is the noise
                                   each Stokes map's summary states
``leakage_<tag>.fits``             I, Q, U, V of the unpolarised sky ``[T, 0, 0, 0]`` imaged
                                   through the same solve: Q, U, V are the leakage of I the beam
                                   model leaves
``polfrac_<tag>.fits``             linear ``sqrt(Q^2 + U^2) / I`` and circular ``V / I``
                                   fractions where I exceeds ``POLFRAC_MIN_I`` of the I peak
``stokes_<tag>_<X>.png``           Mollweide views of Q, U, V and the linear fraction
``vclean_<tag>.fits``              with ``clean.enabled``: the CLEAN of V, columns ``V_RESTORED``
                                   (residual + components convolved with the V PSF's fitted
                                   Gaussian of their declination), ``V_RESIDUAL``, ``V_MODEL``
                                   (components, flux / pixel solid angle)
``vclean_<tag>.png``               the restored V map
``polclean_<tag>.fits``            the full-Stokes CLEAN of the compact sources: I, Q, U, V
                                   restored (residual + each component's I, Q, U, V convolved
                                   with the I PSF's fitted Gaussian of its declination), IAU
=================================  =============================================================
"""
from __future__ import annotations

import numpy as np

from mmflow.conventions import healpy_alm, radec_to_vec
from mmflow.imaging import clean as ck
from mmflow.imaging import psf
from mmflow.imaging.jackknife import noise_realisation, split_variance
from mmflow.imaging.maps import stokes_alm_to_output_maps
from mmflow.io.export import POLARISATION_KEYWORDS, write_healpix_fits, write_mollweide_png
from mmflow.io.run_stores import STORES, CLEAN_STOPS
from mmflow.sky import units
from mmflow.sky.frames import rotation_matrix
from mmflow.workflow.engine import clean_state as cs
from mmflow.workflow.engine.task_key import TaskKey

#: the polarised fraction is shown only where I exceeds this fraction of the map's I peak
POLFRAC_MIN_I = 0.05
COLUMNS = ["I_STOKES", "Q_STOKES", "U_STOKES", "V_STOKES"]


def _maps(ctx, name, fi, nside, unit=None, split=None):
    """I, Q, U, V maps ``(4, npix)`` of stokes.zarr's array ``name`` (``STORES.stokes.alm``, ...) at channel
    ``fi`` (of data split ``split``, an index of ``mmode.splits``, for ``alm``) in ``products.frame`` and ``unit``."""
    cfg = ctx.cfg
    lmax, p = cfg.mmode.lmax, cfg.products
    vis = ctx.open(STORES.vis)
    f, epoch = float(vis[STORES.vis.freqs_hz][fi]), float(vis.attrs["epoch_jd"])
    if split is None:
        padded = ctx.read(name, (slice(fi, fi + 1),))[0]  # (4, m, l)
    else:
        padded = ctx.read(name, (slice(split, split + 1), slice(fi, fi + 1)))[0, 0]
    alm = np.stack([healpy_alm(padded[x], lmax) for x in range(4)])
    maps = stokes_alm_to_output_maps(alm, lmax, f, epoch, p.frame, unit or p.unit, nside)
    ctx.check_finite(f"maps/{name} of channel {fi}", maps)
    return maps


def stokes_noise(ctx, fi, nside, mask, full):
    """The jackknife noise of each Stokes map (``mmode.splits``: even/odd, else per day;
    :func:`mmflow.workflow.engine.clean_state.jackknife_splits`; ``full`` the full data's maps ``(4, npix)``,
    already made): ``(realisation (4, npix) in products.unit,
    {"estimator", "I"..."V": sigma in products.unit})``, or ``(None, None)`` without a jackknife.

    Each split is imaged through the same factorisation as the full data, so the estimators of
    :mod:`mmflow.imaging.jackknife` apply to Q, U and V as to I: the rms over the sky seen
    (``mask``, the output frame) of the jackknife variance map.
    """
    kind, used, fractions = cs.jackknife_splits(ctx, fi)
    if kind is None:
        return None, None
    splits = list(ctx.cfg.mmode.splits)
    maps = {s: full if s == "full" else _maps(ctx, STORES.stokes.alm, fi, nside, split=splits.index(s)) for s in used}
    sigma = {x: float(np.sqrt(split_variance({s: m[k] for s, m in maps.items()}, kind, fractions, mask)))
             for k, x in enumerate("IQUV")}
    return noise_realisation(maps, kind, fractions), {"estimator": kind, "unit": ctx.cfg.products.unit, **sigma}


def _clean_components(ctx, fi, cycles, components):
    """A CLEAN's record in stokes.zarr for channel ``fi``: ``(store, frequency Hz, the rotation from the frame of
    date to products.frame (None for date), cycles run, the components written)``; ``components`` rows are a
    direction then fluxes, all 0 where no component was written."""
    g = ctx.open(STORES.stokes)
    vis = ctx.open(STORES.vis)
    f, epoch = float(vis[STORES.vis.freqs_hz][fi]), float(vis.attrs["epoch_jd"])
    frame = ctx.cfg.products.frame
    rot = None if frame == "date" else rotation_matrix("date", frame, epoch)
    n_cyc = int(g[cycles][fi])
    comps = g[components][fi, :n_cyc]
    comps = comps.reshape(-1, comps.shape[-1])
    return g, f, rot, n_cyc, comps[np.any(comps[:, 3:] != 0, axis=1)]


def v_clean_products(ctx, fi, tag, nside, mask, meta, png):
    """Write the CLEAN of V of channel ``fi`` (``vclean_<tag>.fits``) and return its summary entry."""
    p = ctx.cfg.products
    g, f, rot, n_cyc, comps = _clean_components(ctx, fi, STORES.stokes.v_n_cycles, STORES.stokes.v_components)
    residual = _maps(ctx, STORES.stokes.v_residual, fi, nside, "Jy/sr")[3]
    table = psf.table_from_array(g[STORES.stokes.v_psf_table][fi])
    restored = ck.restore_map(residual, comps[:, :3], comps[:, 3], table, to_frame=rot)
    cols = [units.convert(m, "Jy/sr", p.unit, f) for m in (restored, residual,
                                                         ck.model_map(comps[:, :3], comps[:, 3], nside, rot))]
    ctx.check_finite(f"maps/vclean of channel {fi}", np.stack(cols))
    path = f"maps/vclean_{tag}.fits"
    write_healpix_fits(
        ctx.run.path / path,
        np.stack(cols),
        dict(meta, STOKES="V", CLEANCYC=n_cyc, **POLARISATION_KEYWORDS),
        mask=mask,
        column_names=["V_RESTORED", "V_RESIDUAL", "V_MODEL"],
    )
    ctx.ledger.record_file(ctx.run.path / path)
    info = {"fits": path, "cycles": n_cyc, "components": int(len(comps)), "flux_jy": float(comps[:, 3].sum()),
            "stop": CLEAN_STOPS[int(g[STORES.stokes.v_stop][fi])],
            "threshold_jy_sr": float(g[STORES.stokes.v_threshold][fi]),
            "noise_jy_sr": float(g[STORES.stokes.v_noise][fi]), "restored_peak": float(np.max(np.abs(cols[0][mask])))}
    if png:
        write_mollweide_png(ctx.run.path / f"maps/vclean_{tag}.png", cols[0], f"mmflow {tag} CLEANed Stokes V "
                            f"({p.frame})", p.unit, mask=mask)
        ctx.ledger.record_file(ctx.run.path / f"maps/vclean_{tag}.png")
        info["png"] = f"maps/vclean_{tag}.png"
    return info


def sources_products(ctx, fi, tag, nside, mask, meta):
    """Write the restored maps of the full-Stokes CLEAN of the compact sources of channel ``fi``
    (``polclean_<tag>.fits``: the residual's I, Q, U, V plus each component's, convolved with the I PSF's
    Gaussian of its declination, :func:`mmflow.imaging.clean.restore_map`; Q, U referred to
    ``products.frame``'s north as the residual's are) and return its path."""
    p = ctx.cfg.products
    g, f, rot, n_cyc, comps = _clean_components(ctx, fi, STORES.stokes.src_n_cycles, STORES.stokes.src_components)
    stokes = comps[:, 3:].copy()
    if rot is not None and len(comps):  # Q + iU turns by 2 psi with the frame's north (north_rotation)
        psi = ck.north_rotation(comps[:, :3], rot)
        c, s = np.cos(2 * psi), np.sin(2 * psi)
        stokes[:, 1], stokes[:, 2] = c * comps[:, 4] - s * comps[:, 5], s * comps[:, 4] + c * comps[:, 5]
    residual = _maps(ctx, STORES.stokes.src_residual, fi, nside, "Jy/sr")
    table = psf.table_from_array(g[STORES.stokes.src_psf_table][fi])
    restored = np.stack([units.convert(ck.restore_map(residual[x], comps[:, :3], stokes[:, x], table, to_frame=rot),
                                       "Jy/sr", p.unit, f) for x in range(4)])
    ctx.check_finite(f"maps/polclean of channel {fi}", restored)
    path = f"maps/polclean_{tag}.fits"
    write_healpix_fits(ctx.run.path / path, restored, dict(meta, STOKES="IQUV", POLCONV="avg", CLEANCYC=n_cyc,
                                                           **POLARISATION_KEYWORDS), mask=mask, column_names=COLUMNS)
    ctx.ledger.record_file(ctx.run.path / path)
    return path


def sources_in_frame(entry, frame, epoch_jd):
    """The stokes stage's CLEANed sources (``entry``: its task's ``sources``, frame of date) in ``frame``
    (``products.frame``; ``epoch_jd`` the run's epoch): each source's ``lon_deg``, ``lat_deg`` there and its
    polarisation angle turned by :func:`mmflow.imaging.clean.north_rotation` (north through east in that frame,
    IAU, in [-90, 90)); the Stokes vector and the fractions do not change."""
    if not entry:
        return entry
    rot = None if frame == "date" else rotation_matrix("date", frame, float(epoch_jd))
    out = dict(entry, frame=frame, sources=[])
    for src in entry["sources"]:
        src = dict(src)
        vec = radec_to_vec(np.deg2rad(src.pop("ra_deg")), np.deg2rad(src.pop("dec_deg")))
        if rot is not None:
            if src["angle_deg"] is not None:
                chi = src["angle_deg"] + np.rad2deg(ck.north_rotation(vec[None], rot)[0])
                src["angle_deg"] = float((chi + 90.0) % 180.0 - 90.0)
            vec = rot @ vec
        src["lon_deg"] = float(np.rad2deg(np.arctan2(vec[1], vec[0])) % 360.0)
        src["lat_deg"] = float(np.rad2deg(np.arcsin(np.clip(vec[2], -1, 1))))
        out["sources"].append(src)
    return out


def polarised_fraction(iquv, min_i_fraction=POLFRAC_MIN_I, mask=None):
    """``(sqrt(Q^2 + U^2) / I, V / I)`` where ``I > min_i_fraction`` x the I peak (of the ``mask``ed sky), NaN
    elsewhere."""
    i, q, u, v = iquv
    seen = np.ones(i.shape, bool) if mask is None else np.asarray(mask, bool)
    good = seen & (i > min_i_fraction * np.max(i[seen]))
    safe = np.where(good, i, 1.0)
    return np.where(good, np.hypot(q, u) / safe, np.nan), np.where(good, v / safe, np.nan)


def stokes_products(ctx, fi, tag, nside, mask, meta, png):
    """Write the full-Stokes maps of channel ``fi`` and return their summary entries."""
    maps_dir = ctx.run.path / "maps"
    iquv, leak = _maps(ctx, STORES.stokes.alm, fi, nside, split=0), _maps(ctx, STORES.stokes.leakage, fi, nside)
    pmeta = dict(meta, STOKES="IQUV", POLCONV="avg", **POLARISATION_KEYWORDS)
    files = {"stokes_fits": f"maps/stokes_{tag}.fits", "leakage_fits": f"maps/leakage_{tag}.fits",
             "polfrac_fits": f"maps/polfrac_{tag}.fits"}
    write_healpix_fits(ctx.run.path / files["stokes_fits"], iquv, pmeta, mask=mask, column_names=COLUMNS)
    write_healpix_fits(ctx.run.path / files["leakage_fits"], leak, dict(pmeta, LEAKAGE=True), mask=mask,
                       column_names=COLUMNS)
    lin, circ = polarised_fraction(iquv, mask=mask)
    seen_frac = mask & np.isfinite(lin)
    write_healpix_fits(ctx.run.path / files["polfrac_fits"], np.stack([np.nan_to_num(lin), np.nan_to_num(circ)]),
                       dict(pmeta, BUNIT="", MINIFRAC=POLFRAC_MIN_I), mask=seen_frac, column_names=["P_LIN", "P_CIRC"])
    noise_map, noise = stokes_noise(ctx, fi, nside, mask, iquv)
    if noise is not None:
        files["noise_fits"] = f"maps/stokes_noise_{tag}.fits"
        write_healpix_fits(ctx.run.path / files["noise_fits"], noise_map, dict(pmeta, JACKKNIF=noise["estimator"]),
                           mask=mask, column_names=COLUMNS)
    for q in files.values():
        ctx.ledger.record_file(ctx.run.path / q)
    i_peak = float(np.max(iquv[0][mask]))
    info = dict(files)
    info["stokes_peak"] = {s: float(np.max(np.abs(m[mask]))) for s, m in zip("IQUV", iquv)}
    if noise is not None:
        info["noise"] = noise
    # the largest leakage of the unpolarised sky into each of Q, U, V, relative to the I peak
    info["leakage_max_fraction"] = {s: float(np.max(np.abs(m[mask])) / i_peak) for s, m in zip("QUV", leak[1:])}
    # whether the solve images polarised fractions as they are (the polarisation_response of the stokes
    # stage's second phase, its per-frequency task of cycle 0)
    task = ctx.run.task_infos("stokes").get(TaskKey(freq=fi, cycle=0).format(), {})
    info["polarisation"] = task.get("polarisation")
    # the compact sources' Stokes vectors from the full-Stokes CLEAN through the run's response (unbiased where
    # measured: each source's cond(A) <= cond_max), in products.frame
    info["sources"] = sources_in_frame(task.get("sources"), ctx.cfg.products.frame,
                                       ctx.open(STORES.vis).attrs["epoch_jd"])
    if info["sources"]:
        info["sources"]["fits"] = sources_products(ctx, fi, tag, nside, mask, meta)
    if png:
        views = {"Q": iquv[1], "U": iquv[2], "V": iquv[3], "plin": np.where(seen_frac, lin, 0.0)}
        for name, hmap in views.items():
            path = maps_dir / f"stokes_{tag}_{name}.png"
            unit = "" if name == "plin" else ctx.cfg.products.unit
            write_mollweide_png(path, hmap, f"mmflow {tag} Stokes {name} (IAU, {ctx.cfg.products.frame})", unit,
                                mask=seen_frac if name == "plin" else mask)
            ctx.ledger.record_file(path)
        info["stokes_png"] = [f"maps/stokes_{tag}_{n}.png" for n in views]
    if ctx.cfg.clean.enabled:
        info["v_clean"] = v_clean_products(ctx, fi, tag, nside, mask, meta, png)
    return info
