"""Checks that need more than one field, or a file, before any cluster starts or stage runs.

Each check returns :class:`~mmflow.workflow.config.errors.Problem` records (location, value,
what is wrong, the fix); :func:`check_config` runs them all so that one error lists every
problem. The antenna selection and the beam are built here exactly as the stages build them,
so a selection that keeps no antennas or a beam that does not cover a channel is refused
before any work.
"""
from __future__ import annotations

import ipaddress
import re
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from mmflow.conventions import SIDEREAL_DAY_S, drift_scan_lsts, is_full_stokes
from mmflow.errors import InputError
from mmflow.mmode.splits import day_index, day_splits, jackknife_kind, sidereal_times_jd, split_problems
from mmflow.sky.sources import CATALOG
from mmflow.telescope.layout import selected_layout
from mmflow.telescope.beam_factory import make_beam, make_jones
from mmflow.workflow.config.beam import BEAM_PARAMS
from mmflow.workflow.config.errors import Problem, from_pydantic, nearest, show
from mmflow.workflow.engine.geometry import n_bins_of, n_integrations, run_freqs_hz
from mmflow.workflow.engine.prior_run import prior_run_problems
from mmflow.paths import expand_path


def beam_problems(beam):
    """Validate the raw ``beam`` mapping's parameters against the model of its type."""
    if not isinstance(beam, dict) or beam.get("type", "sin_elevation") not in BEAM_PARAMS:
        return []  # the schema reports a wrong section or type
    model = BEAM_PARAMS[beam.get("type", "sin_elevation")]
    params = {k: v for k, v in beam.items() if k != "type"}
    try:
        model.model_validate(params)
    except ValidationError as exc:
        out = from_pydantic(exc.errors(), model, prefix=("beam",))
        kind = beam.get("type", "sin_elevation")
        for p in out:
            p.problem = p.problem.replace("not an option of beam ", f"not a parameter of beam type '{kind}' ")
            p.fix = p.fix.replace("options of the top level", f"parameters of beam type '{kind}'")
            other = [k for k, m in BEAM_PARAMS.items() if k != kind and str(p.loc[-1]) in m.model_fields]
            if "not a parameter" in p.problem and other:
                names = ", ".join(f.alias or n for n, f in model.model_fields.items())
                p.fix = (f"'{p.loc[-1]}' belongs to beam type '{other[0]}': to change the type, replace the "
                         f"whole section, e.g. beam={{type: {kind}, ...}} (parameters: {names})")
        return out
    return []


def _exists(path):
    return Path(expand_path(path)).exists()


def _telescope_problems(cfg):
    t = cfg.telescope
    out = []
    if t.layout_file is not None:
        if t.preset is not None:
            out.append(Problem(("telescope", "preset"), t.preset, f"preset {show(t.preset)} and layout_file "
                               f"{show(t.layout_file)} both given", "keep one: set telescope.preset: null to use "
                               "the layout file, or remove telescope.layout_file"))
        for key in ("lat_deg", "lon_deg"):
            if getattr(t, key) is None:
                out.append(Problem(("telescope", key), None, "a layout file needs the site",
                                   f"set telescope.{key} (degrees) of the array centre"))
        if not _exists(t.layout_file):
            out.append(Problem(("telescope", "layout_file"), t.layout_file, "file not found",
                               "give the path of a text layout 'name east north [up]'"))
    else:
        if t.preset is None:
            out.append(Problem(("telescope", "preset"), None, "no array: neither a preset nor a layout_file",
                               "set telescope.preset (core, full, paper-2017, leda512-2013) or telescope.layout_file"))
        for key in ("lat_deg", "lon_deg"):
            if getattr(t, key) is not None:
                out.append(Problem(("telescope", key), getattr(t, key), "only used with layout_file "
                                   f"(preset {show(t.preset)} has its own site)", f"remove telescope.{key}"))
    if out or cfg.source != "simulate":  # ingested data carry their own layout
        return out
    return _selection_problems(cfg)


def _selection_problems(cfg):
    """Build the antenna selection as the simulate stage will, and check it."""
    t = cfg.telescope
    try:
        full, lay = selected_layout(t.preset, t.layout_file, t.lat_deg, t.lon_deg, t.radius_m, t.stands,
                                    t.max_antennas)
    except InputError as exc:
        loc = ("telescope", "stands") if exc.field == "stands" else ("telescope", "layout_file")
        return [Problem(loc, None, f"{exc.what}: {exc.problem}", exc.fix)]
    out = []
    what = f"preset {show(t.preset)}" if t.layout_file is None else f"layout {show(t.layout_file)}"
    if lay.n_ant < 2:
        r = np.sort(np.hypot(full.enu[:, 0], full.enu[:, 1]))
        if t.radius_m is not None and len(r) >= 2 and t.radius_m < r[1]:
            loc, val, fix = ("telescope", "radius_m"), t.radius_m, (
                f"use telescope.radius_m >= {np.ceil(r[1] * 10) / 10:g} (the second-closest stand of {what})")
        elif t.stands is not None:
            loc, val, fix = ("telescope", "stands"), t.stands, "list at least two stand names of the layout"
        else:
            loc, val, fix = ("telescope", "max_antennas"), t.max_antennas, "keep at least two antennas"
        n = "no antennas" if lay.n_ant == 0 else "one antenna (no baselines to image with)"
        out.append(Problem(loc, val, f"the selection from {what} keeps {n}", fix))
    dup = lay.duplicates()
    if dup:
        out.append(Problem(("telescope", "layout_file" if t.layout_file else "preset"), None,
                           f"{what} has {dup}", "give every antenna a unique name and position"))
    return out


def _beam_build_problems(cfg):
    """Build the beam as the stages do and check it covers every channel."""
    spec = cfg.beam.model_dump()
    if spec.get("type") == "pyuvdata" and spec.get("file") and not _exists(spec["file"]):
        return [Problem(("beam", "file"), spec["file"], "file not found",
                        "give the path of a beam file pyuvdata reads")]
    try:
        beam = make_beam(spec)
        for f in _run_freqs_hz(cfg):
            beam.check_frequency(f)
    except InputError as exc:
        loc = ("observation", "freqs_mhz") if exc.field in ("frequency", "freq_array") else ("beam",)
        return [Problem(loc, None, f"beam type {show(spec.get('type'))}: {exc.problem}", exc.fix)]
    except Exception as exc:  # pyuvdata's analytic beams raise their own errors for bad params
        return [Problem(("beam", "params"), spec.get("params"), f"pyuvdata cannot build the beam ({exc})",
                        "give the arguments of that pyuvdata.analytic_beam class")]
    return []


def _run_freqs_hz(cfg):
    """The run's channels as its telescope takes them (:func:`mmflow.workflow.engine.geometry.run_freqs_hz`); none
    where the input files cannot be planned (the ingest stage's check reports why, naming the files)."""
    if cfg.source != "ingest":
        return run_freqs_hz(cfg)
    from mmflow.workflow.engine.ingest_plan import (
        ingest_plan,
    )  # deferred: reading a simulation's config imports no numerics

    try:
        return run_freqs_hz(cfg, ingest_plan(cfg))
    except InputError:
        return []


def _value_problems(cfg):
    out = []
    mm, ob = cfg.mmode, cfg.observation
    mmax = mm.lmax if mm.mmax is None else mm.mmax
    if mm.mmax is not None and mm.mmax > mm.lmax:
        out.append(Problem(("mmode", "mmax"), mm.mmax, f"larger than mmode.lmax = {mm.lmax}",
                           f"set mmode.mmax <= {mm.lmax}, or null for mmax = lmax"))
    if mm.n_bins is not None and mm.n_bins < 2 * mmax + 1:
        out.append(Problem(("mmode", "n_bins"), mm.n_bins, f"too few sidereal bins to resolve m up to {mmax}",
                           f"use mmode.n_bins >= {2 * mmax + 1} (2 mmax + 1), or null"))
    if cfg.source == "simulate":
        per_day = SIDEREAL_DAY_S / ob.integration_s
        if mm.n_bins is None and round(per_day) < 2 * mmax + 1:
            out.append(Problem(("observation", "integration_s"), ob.integration_s,
                               f"{round(per_day)} integrations per sidereal day cannot resolve m up to {mmax}",
                               f"use observation.integration_s <= {SIDEREAL_DAY_S / (2 * mmax + 1):.4g} s, "
                               f"or a smaller mmode.lmax"))
        if ob.n_integrations is not None and ob.n_integrations / per_day < mm.min_coverage:
            out.append(Problem(("observation", "n_integrations"), ob.n_integrations,
                               f"covers {ob.n_integrations / per_day:.1%} of the sidereal day, less than "
                               f"mmode.min_coverage = {mm.min_coverage:g}",
                               f"simulate at least {int(np.ceil(mm.min_coverage * per_day))} integrations, "
                               f"or null for a whole day"))
        if cfg.sky.noise and not cfg.telescope.include_autos:
            out.append(Problem(("sky", "noise"), True, "thermal noise is drawn from the autocorrelations, "
                               "but telescope.include_autos is false",
                               "set telescope.include_autos: true, or sky.noise: false"))
        if cfg.sky.sources:
            out.extend(_source_problems(cfg.sky.sources))
        if ob.raw_files and not (cfg.corrupt.enabled or is_full_stokes(cfg.imaging.stokes)):
            out.append(Problem(("observation", "raw_files"), ob.raw_files, "a clean Stokes-I simulation has no "
                               "correlations to write (it makes I alone, not a feed's XX and YY)",
                               "set corrupt.enabled: true (XX, YY as a telescope records them) or "
                               "imaging.stokes: [I, Q, U, V] (the four correlations), or raw_files: null"))
        if cfg.corrupt.enabled:
            out.extend(_source_problems(cfg.corrupt.dd_sources, ("corrupt", "dd_sources")))
            out.extend(_not_among(("corrupt", "dd_sources"), cfg.corrupt.dd_sources, cfg.sky.sources, "sky.sources",
                                  "add them to sky.sources, or remove them from corrupt.dd_sources"))
    if cfg.calibrate.enabled:
        out.extend(_calibrate_problems(cfg.calibrate))
    if cfg.peel.enabled:
        out.extend(_source_problems(cfg.peel.sources, ("peel", "sources")))
        out.extend(_not_among(("peel", "peel"), cfg.peel.peel, cfg.peel.sources, "peel.sources",
                              "list the peeled sources in peel.sources too"))
        out.extend(_source_problems(cfg.peel.model_sources, ("peel", "model_sources")))
        out.extend(_duplicates(("peel", "sources"), cfg.peel.sources))
        out.extend(_duplicates(("peel", "model_sources"), cfg.peel.model_sources))
        both = [n for n in cfg.peel.model_sources if n in cfg.peel.sources]
        if both:
            out.append(Problem(("peel", "model_sources"), both, "listed in peel.sources too: a source is either "
                               "removed or modelled and kept", "remove them from one of the two lists"))
    if cfg.models.enabled:
        out.extend(_models_problems(cfg))
    if mm.noise == "radiometer" and not cfg.telescope.include_autos:
        out.append(Problem(("mmode", "noise"), "radiometer", "the radiometer equation needs the autocorrelations",
                           "set telescope.include_autos: true, or mmode.noise: data (or auto)"))
    if mm.prior_run is not None:
        out.extend(_prior_run_problems(cfg))
    im = cfg.imaging
    if im.method == "prior" and im.prior_map is None:
        out.append(Problem(("imaging", "prior_map"), None, "method 'prior' needs a prior map",
                           "set imaging.prior_map to a HEALPix FITS file, or choose another imaging.method"))
    if im.prior_map is not None and not _exists(im.prior_map):
        out.append(Problem(("imaging", "prior_map"), im.prior_map, "file not found",
                           "give the path of a HEALPix FITS map"))
    run_dir = Path(cfg.run.directory)
    if run_dir.exists() and not run_dir.is_dir():
        out.append(Problem(("run", "directory"), cfg.run.directory, "is a file, not a directory",
                           "give a new or existing directory for the run"))
    out.extend(_cluster_problems(cfg.cluster))
    return out


def _models_problems(cfg):
    """The fitted models are used by peel: each fitted source must be among peel.sources (peel enabled)."""
    m = cfg.models
    out = _source_problems(m.sources, ("models", "sources"))
    if not cfg.peel.enabled:
        out.append(Problem(("models", "enabled"), True, "the fitted models are used only by the peel stage, "
                           "which is disabled", "set peel.enabled: true, or models.enabled: false"))
    out.extend(_not_among(("models", "sources"), m.sources, cfg.peel.sources, "peel.sources",
                          "fit only sources that peel removes"))
    out.extend(_duplicates(("models", "sources"), m.sources))
    for key in ("components", "size_arcmin"):  # per-source settings: a misspelt name would be ignored
        for name in getattr(m, key):
            out.extend(_source_problems([name], ("models", key)))
    bad = {k: v for k, v in m.components.items() if v < 1}
    if bad:
        out.append(Problem(("models", "components"), bad, "a source needs at least one component", "use >= 1"))
    bad = {k: v for k, v in m.size_arcmin.items() if not v > 0}
    if bad:
        out.append(Problem(("models", "size_arcmin"), bad, "sizes must be positive", "use sizes > 0 arcmin"))
    return out


def _duplicates(field, names):
    """A name listed twice (a source fitted twice: two identical columns of one fit)."""
    twice = sorted({n for n in names if list(names).count(n) > 1})
    if not twice:
        return []
    return [Problem(field, twice, "listed more than once", "list each source once")]


def _prior_run_problems(cfg):
    """``mmode.prior_run`` holds a finished run with this run's lmax (and, for simulated data, channels and
    epoch; ingested data are checked by the mmodes stage once their channels and epoch are known)."""
    mm, ob = cfg.mmode, cfg.observation
    sim = cfg.source == "simulate"
    found = prior_run_problems(
        mm.prior_run,
        mm.lmax,
        mm.lmax if mm.mmax is None else mm.mmax,
        cfg.run.directory,
        np.asarray(ob.simulated_freqs_mhz()) * 1e6 if sim else None,
        ob.epoch_jd if sim else None,
    )
    return [Problem(("mmode", "prior_run"), mm.prior_run, problem, fix) for problem, fix in found]


def _not_among(field, names, pool, pool_name, fix):
    """A problem for the ``names`` that ``pool`` (the setting ``pool_name``) lacks, if any."""
    missing = [n for n in names if n not in pool]
    return [Problem(field, missing, f"not among {pool_name}", fix)] if missing else []


def _calibrate_problems(c):
    out = _source_problems(c.sources, ("calibrate", "sources"))
    out.extend(_source_problems(c.screen_sources, ("calibrate", "screen_sources")))
    screened = [n for n in c.screen_sources if n in c.sources]
    out.extend(_not_among(("calibrate", "measure_flux"), c.measure_flux, screened,
                          "calibrate.screen_sources and calibrate.sources",
                          "a measured flux is the mean of a screened source's flux factors: list it in both"))
    if screened and c.measure_flux and all(n in c.measure_flux for n in screened):
        out.append(Problem(("calibrate", "measure_flux"), list(c.measure_flux), "measures every screened source: "
                           "none is left to set the flux scale", "keep at least one screened source (e.g. Cyg A, "
                           "on the Baars scale) out of calibrate.measure_flux"))
    return out


def _source_problems(names, field=("sky", "sources")):
    out = []
    for n in names:
        if n not in CATALOG:
            hit = nearest(n, CATALOG)
            out.append(Problem(field, n, "not in the source catalogue",
                               f"did you mean '{hit}'?" if hit else f"use names from {sorted(CATALOG)}"))
    return out


def _cluster_problems(c):
    out = []
    host = c.dashboard_address.rpartition(":")[0].strip("[]")
    if host and not c.expose and not _is_loopback(host):
        out.append(Problem(("cluster", "dashboard_address"), c.dashboard_address,
                           "listens beyond this machine while cluster.expose is false",
                           "write ':8787' (loopback), or set cluster.expose: true to listen on the network"))
    if c.kind == "address" and c.address is not None and "://" not in c.address and ":" not in c.address:
        out.append(Problem(("cluster", "address"), c.address, "not a scheduler address",
                           "write e.g. tcp://host:8786"))
    logs = c.jobqueue.get("log_directory")
    unset = re.search(r"\$\{?\w+\}?", logs) if isinstance(logs, str) and c.kind in ("slurm", "pbs") else None
    if unset:  # the schema expanded every variable that is set (mmflow.paths.expand_path)
        out.append(Problem(("cluster", "jobqueue", "log_directory"), logs,
                           f"{unset.group(0)} is not set in this environment (SLURM and PBS do not expand "
                           "variables in their job options: a directory would be named so)",
                           "set the variable before running mmflow, or write the path out"))
    return out


def _is_loopback(host):
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _clean_problems(cfg):
    """CLEAN's settings against the rest: a threshold to stop at, peaks apart, the high-pass below lmax."""
    c, lmax = cfg.clean, cfg.mmode.lmax
    if not c.enabled:
        return []
    out = []
    if cfg.imaging.method not in ("tikhonov", "min_variance"):
        out.append(Problem(("imaging", "method"), cfg.imaging.method, "CLEAN observes its components through "
                           "(G + eps I)^-1 G, the Tikhonov operator; this method makes another PSF",
                           "use imaging.method: tikhonov (or min_variance) with clean.enabled, "
                           "or clean.enabled: false"))

    if jackknife_kind(cfg.mmode.splits) is None and c.threshold is None and c.rel_threshold == 0:
        out.append(Problem(("clean", "threshold"), None, "CLEAN stops at threshold_sigma x the jackknife noise, "
                           f"but mmode.splits = {list(cfg.mmode.splits)} has no even and odd halves and no day<k> "
                           "splits to estimate it", "set mmode.splits=[full, even, odd] (one transfer pass for all; "
                           "or day0, day1, ... for data of several days), or give clean.threshold "
                           "(in clean.threshold_unit) or clean.rel_threshold"))
    if c.min_separation_deg < 180.0 / lmax:
        out.append(Problem(("clean", "min_separation_deg"), c.min_separation_deg,
                           f"closer than the resolution 180 / lmax = {180.0 / lmax:.3g} deg: peaks of one cycle "
                           "would fall in one main lobe", f"use clean.min_separation_deg >= {180.0 / lmax:.3g} "
                           "(a few PSF widths)"))
    if c.highpass_lmin is not None:
        if c.highpass_lmin >= lmax:
            out.append(Problem(("clean", "highpass_lmin"), c.highpass_lmin, f"not below mmode.lmax = {lmax}: "
                               "nothing would be CLEANed", f"use clean.highpass_lmin < {lmax}, or null (off)"))
        if c.highpass_width > c.highpass_lmin:
            out.append(Problem(("clean", "highpass_width"), c.highpass_width, "wider than highpass_lmin = "
                               f"{c.highpass_lmin}", f"use clean.highpass_width <= {c.highpass_lmin}"))
    return out


def _split_problems(cfg):
    """``day<k>`` splits of a simulation against the days it simulates (the stage checks ingested data,
    and ``day`` / ``night``, in its prepare: :func:`mmflow.mmode.splits.split_problems`). The days are
    counted as the stage counts them, from LSTs and times (the simulation's times advance at the
    sidereal rate: :func:`mmflow.mmode.splits.sidereal_times_jd`)."""
    mm, ob = cfg.mmode, cfg.observation
    if cfg.source != "simulate":
        return []
    n_bins = n_bins_of(cfg, ob.integration_s)
    if {"even", "odd"} & set(mm.splits) and n_bins % 2:
        return [Problem(("mmode", "n_bins"), mm.n_bins, f"even/odd splits need an even number of sidereal bins; "
                        f"{'this gives' if mm.n_bins else f'observation.integration_s = {ob.integration_s:g} s gives'}"
                        f" {n_bins}", f"set mmode.n_bins={n_bins + 1} (or {n_bins - 1})")]
    if not day_splits(mm.splits):
        return []
    lsts = drift_scan_lsts(np.deg2rad(ob.start_lst_deg), ob.integration_s, np.arange(n_integrations(cfg)))
    days = day_index(lsts, sidereal_times_jd(lsts))
    return [Problem(("mmode", "splits"), name, problem, fix)
            for name, problem, fix in split_problems(mm.splits, lsts, days, None, n_bins, mm.min_coverage)]


def _products_problems(cfg):
    """The science products' settings: catalogue names, an annulus outside the disc."""
    p = cfg.products
    out = []
    if p.flux_scale_sources is not None:
        out.extend(_source_problems(p.flux_scale_sources, ("products", "flux_scale_sources")))
    inner, outer = p.flux_annulus_fwhm
    if not p.flux_disc_fwhm <= inner < outer:
        out.append(Problem(("products", "flux_annulus_fwhm"), list(p.flux_annulus_fwhm),
                           f"not an annulus outside the flux disc (radius {p.flux_disc_fwhm} FWHM)",
                           "give [inner, outer] with flux_disc_fwhm <= inner < outer, e.g. [1.2, 2.0]"))
    return out


def _polarised_sky_problems(cfg):
    """``sky.polarised``: sources of ``sky.sources``, fractions of at most 1, and a run that images them."""
    pol = cfg.sky.polarised
    if not pol:
        return []
    out = []
    for name, (q, u, v) in pol.items():
        loc = ("sky", "polarised", name)
        if name not in cfg.sky.sources:
            hit = nearest(name, cfg.sky.sources)
            out.append(Problem(loc, [q, u, v], f"'{name}' is not in sky.sources {list(cfg.sky.sources)}",
                               "add it to sky.sources" + (f" (or did you mean '{hit}'?)" if hit else "")))
        p = float(np.sqrt(q * q + u * u + v * v))  # (NaN and inf: refused by the schema)
        if p > 1.0:
            out.append(Problem(loc, [q, u, v], f"polarised fraction sqrt(q^2 + u^2 + v^2) = {p:.3g} is more than 1",
                               "give fractions of I"))
    if cfg.source != "simulate" or not is_full_stokes(cfg.imaging.stokes):
        out.append(Problem(("sky", "polarised"), dict(pol), "only a full-Stokes simulation carries polarisation "
                           f"(source: {cfg.source}, imaging.stokes: {list(cfg.imaging.stokes)})",
                           "set source=simulate and imaging.stokes=[I, Q, U, V], or sky.polarised={}"))
    return out


def _stokes_problems(cfg):
    """Full Stokes (``imaging.stokes: [I, Q, U, V]``): what it needs of the input, the beam and the stages;
    polarisation leakage, which only a simulation of the four correlations carries."""
    if not is_full_stokes(cfg.imaging.stokes):
        if cfg.source == "simulate" and cfg.corrupt.enabled and cfg.corrupt.leakage > 0:
            return [Problem(("corrupt", "leakage"), cfg.corrupt.leakage, "polarisation leakage mixes the four "
                            "correlations: a simulation of xx and yy alone cannot carry it",
                            "set imaging.stokes=[I, Q, U, V] (and a beam with feeds), or corrupt.leakage=0")]
        return []
    out = []
    if cfg.source != "simulate" and not cfg.input.cross_hands:
        out.append(Problem(("input", "cross_hands"), False, "full Stokes needs the cross hands xy, yx",
                           "set input.cross_hands=true"))
    mm = cfg.mmode
    if mm.mmax is not None and mm.mmax != mm.lmax:
        out.append(Problem(("mmode", "mmax"), mm.mmax, f"full Stokes solves every m up to lmax = {mm.lmax}",
                           "set mmode.mmax=null"))
    try:
        make_jones(cfg.beam.model_dump())
    except InputError as exc:
        out.append(Problem(("beam", "type"), cfg.beam.type, exc.problem, exc.fix))
    return out


def check_config(cfg):
    """Every cross-field and file problem of a schema-valid configuration (empty list: fine)."""
    out = _telescope_problems(cfg) + _value_problems(cfg) + _clean_problems(cfg) + _products_problems(cfg) + \
        _split_problems(cfg) + _polarised_sky_problems(cfg)
    if not any(p.loc[:1] == ("beam",) for p in out):
        out.extend(_beam_build_problems(cfg))
        out.extend(_stokes_problems(cfg))
    return out
