"""Data splits of a drift scan: which integrations (or sidereal bins) each split holds.

Two kinds of split travel through the m-modes, right-hand sides and alm (``mmode.splits``),
all projected by one transfer pass:

* **bin parities** ``even`` / ``odd``: the even (``n = 2k``) or odd (``n = 2k + 1``) sidereal
  bins of the full grid (:func:`mmflow.mmode.transform.split_mmode_transform`); every
  integration of every day goes to one of them;
* **time subsets** ``day<k>``, ``day``, ``night``: a subset of the integrations, binned on its
  own (:func:`mmflow.mmode.transform.sidereal_bins`) and fitted like the full data
  (:func:`mmflow.mmode.gapfill.chunk_mmodes`):

  - ``day<k>`` (``k = 0, 1, ...``): the integrations of the k-th sidereal day counted from the
    earliest integration's LST, ``k_n = round((Omega (t_n - t_0) - [(phi_n - phi_0) mod 2 pi]) / 2 pi)``
    with ``Omega = 2 pi / 86164.0905 s`` (:func:`day_index`): the elapsed sidereal angle less
    the wrapped LST difference is a whole number of turns;
  - ``day`` / ``night``: integrations with the Sun's centre above / below the horizon at the
    site (geometric elevation > 0 / <= 0, no refraction; :func:`sun_elevation_deg`).

A time subset measures the sky only at the LSTs it covers: one day of data splits into a day
half and a night half that each see only part of the sidereal day, so ``day`` / ``night`` is a
jackknife only for data spanning months (the Sun's RA moves ~1 deg a day). The stage refuses
(:func:`split_problems`) a ``day`` / ``night`` split covering less than ``mmode.min_coverage`` of
the sidereal bins (:func:`bin_coverage`) and, with any ``day<k>`` listed, any day of the data
that does (the per-day jackknife needs whole days); each task checks every time split's
unflagged bins the same way. Each split's share ``f_k`` of the data is counted from the flags
(:func:`split_shares` of the mmodes stage's ``n_samples``).

Plain numpy (and astropy for the Sun); no dask, no configuration.
"""
from __future__ import annotations

import re

import numpy as np
from astropy import units as u
from astropy.time import Time

from mmflow.conventions import SIDEREAL_DAY_S, TWO_PI
from mmflow.mmode.transform import bin_index

PARITY_SPLITS = ("full", "even", "odd")  # splits of the sidereal bins (every integration used)
SUN_SPLITS = ("day", "night")
_DAY = re.compile(r"^day(0|[1-9][0-9]*)$")


def split_kind(name):
    """``("full" | "parity" | "day" | "sun", k)`` of a split name (``k`` the day of ``day<k>``, else None).

    Raises ValueError for a name that is none of ``full``, ``even``, ``odd``, ``day<k>``, ``day``, ``night``.
    """
    if name == "full":
        return "full", None
    if name in ("even", "odd"):
        return "parity", None
    if name in SUN_SPLITS:
        return "sun", None
    hit = _DAY.match(str(name))
    if hit:
        return "day", int(hit.group(1))
    raise ValueError(f"unknown split '{name}'")


def is_time_split(name):
    """True for the splits that select integrations (``day<k>``, ``day``, ``night``)."""
    return split_kind(name)[0] in ("day", "sun")


def day_splits(names):
    """``{k: name}`` of the ``day<k>`` splits among ``names``."""
    return {split_kind(s)[1]: s for s in names if split_kind(s)[0] == "day"}


def jackknife_kind(names):
    """The jackknife that splits ``names`` allow: ``"even_odd"`` when both halves are there (the
    paper's), else ``"per_day"`` with ``day<k>`` splits, else None
    (:func:`mmflow.imaging.jackknife.split_variance`)."""
    if {"even", "odd"} <= set(names):
        return "even_odd"
    return "per_day" if day_splits(names) else None


def day_index(lsts, times_jd=None):
    """Sidereal day of each integration, counted from the earliest one (0, 1, ...).

    With UTC times: ``k_n = round((Omega (t_n - t_0) - [(phi_n - phi_0) mod 2 pi]) / 2 pi)``,
    ``Omega = 2 pi / 86164.0905 s``, ``t_0``, ``phi_0`` the earliest integration's: exact
    whatever the gaps and the row order, as long as the times are good to a fraction of a day
    (the day turns over where the LST passes the earliest integration's). The wrapped difference
    is taken as ``((phi_n - phi_0 + 1e-9) mod 2 pi) - 1e-9``: on a regular grid the LST one turn
    later is ``phi_0 + 2 pi`` up to rounding, which must give 0 (the next day), not ``2 pi - eps``.
    Without times (or where a time is NaN): the turns of the unwrapped LSTs (in row order, from
    row 0), which holds only for data in time order without gaps longer than half a sidereal day.

    Parameters
    ----------
    lsts : ndarray (n_time,)
        Sidereal angle of each integration (rad).
    times_jd : ndarray (n_time,), optional
        UTC Julian date of each integration.

    Returns
    -------
    ndarray (n_time,) int
    """
    phi = np.asarray(lsts, float)
    if phi.size == 0:
        return np.zeros(0, int)
    unwrapped = np.floor((np.unwrap(phi) - phi[0]) / TWO_PI + _TURN_TOL).astype(int)
    if times_jd is None:
        return unwrapped
    t = np.asarray(times_jd, float)
    if not np.isfinite(t).any():
        return unwrapped
    i0 = int(np.nanargmin(t))
    wrapped = np.mod(phi - phi[i0] + _TURN_TOL, TWO_PI) - _TURN_TOL
    turns = (t - t[i0]) * 86400.0 * TWO_PI / SIDEREAL_DAY_S
    with np.errstate(invalid="ignore"):
        k = np.round((turns - wrapped) / TWO_PI)
    return np.where(np.isfinite(k), np.nan_to_num(k), unwrapped).astype(int)


_TURN_TOL = 1e-9  # rad: an LST this close below a whole turn from the first is on the next turn


def sidereal_times_jd(lsts, t0_jd=0.0):
    """Times (JD) of consecutive integrations ``lsts`` (rad, in time order, no gaps) at the sidereal
    rate: ``t_n = t_0 + (unwrap(phi)_n - phi_0) T_sid / (2 pi 86400 s)``, as a simulation's
    ``time_jd`` (:func:`mmflow.simulate.corrupt.utc_at_lsts`) up to the apparent LST's wobble."""
    phi = np.unwrap(np.asarray(lsts, float))
    return t0_jd + (phi - phi[0]) * SIDEREAL_DAY_S / (TWO_PI * 86400.0)


SUN_GRID_S = 300.0  # s: the Sun's elevation is evaluated on this grid and interpolated (error <~ 0.005 deg)


def sun_elevation_deg(times_jd, lat_deg, lon_deg, height_m=0.0, grid_s=SUN_GRID_S):
    """Geometric elevation (deg, no refraction) of the Sun's centre at the site at each UTC time.

    astropy's ``get_body("sun")`` (apparent, geocentric) to ``AltAz`` at the site; offline
    (:mod:`mmflow.offline`, set up by ``import mmflow``). astropy is slow per time (docs/performance.md), so
    where the times outnumber a ``grid_s`` grid over their span the elevation is computed on
    the grid and interpolated linearly: the error is at most ``h^2 / 8`` times the largest
    second derivative, ``A (2 pi / day)^2`` for a daily swing of amplitude ``A <= 90`` deg,
    i.e. ``90 deg (300 s 2 pi / 86400 s)^2 / 8`` ≈ 0.005 deg for 300 s at most (near culmination;
    at the horizon crossings, which decide day / night, far less: the elevation is nearly linear there).
    """
    t = np.asarray(times_jd, float)
    good = np.isfinite(t)
    if good.any():
        lo, hi = float(t[good].min()), float(t[good].max())
        grid = lo + np.arange(int(np.ceil((hi - lo) * 86400.0 / grid_s)) + 2) * grid_s / 86400.0
        if len(grid) < good.sum():
            out = np.full(t.shape, np.nan)
            out[good] = np.interp(t[good], grid, _sun_elevation_deg(grid, lat_deg, lon_deg, height_m))
            return out
    return _sun_elevation_deg(t, lat_deg, lon_deg, height_m)


def _sun_elevation_deg(times_jd, lat_deg, lon_deg, height_m):
    """:func:`sun_elevation_deg` by astropy at every time."""
    # deferred: astropy.coordinates takes 0.1-0.2 s to import (docs/performance.md)
    from astropy.coordinates import AltAz, EarthLocation, get_body

    t = np.asarray(times_jd, float)
    out = np.full(t.shape, np.nan)
    good = np.isfinite(t)
    if not good.any():
        return out
    loc = EarthLocation.from_geodetic(lon=lon_deg * u.deg, lat=lat_deg * u.deg, height=height_m * u.m)
    when = Time(t[good], format="jd", scale="utc")
    sun = get_body("sun", when, location=loc)
    out[good] = sun.transform_to(AltAz(obstime=when, location=loc)).alt.deg
    return out


def split_masks(names, days=None, sun_elevation=None):
    """``{name: bool (n_time,)}``: the integrations of each time-subset split in ``names``.

    ``days``: :func:`day_index` (for ``day<k>``); ``sun_elevation``: :func:`sun_elevation_deg`
    (for ``day`` = elevation > 0, ``night`` = elevation <= 0; NaN: neither). Bin-parity splits
    (``full``, ``even``, ``odd``) select no integrations and are left out.
    """
    out = {}
    for s in names:
        kind, k = split_kind(s)
        if kind == "day":
            out[s] = np.asarray(days) == k
        elif kind == "sun":
            el = np.asarray(sun_elevation, float)
            with np.errstate(invalid="ignore"):
                out[s] = el > 0 if s == "day" else el <= 0
    return out


def bin_coverage(lsts, n_bins):
    """Fraction of the ``n_bins`` sidereal bins that hold at least one of the integrations ``lsts``
    (the bins of :func:`mmflow.mmode.transform.bin_index`)."""
    lsts = np.asarray(lsts, float)
    lsts = lsts[np.isfinite(lsts)]
    if lsts.size == 0:
        return 0.0
    return float(len(np.unique(bin_index(lsts, n_bins)[0])) / n_bins)


def split_shares(counts, names):
    """Each split's share of the data: ``{name: f_k}``, ``f_k = n_k / n_full`` from the unflagged
    sample counts ``counts`` (one per split in ``names``, ``full`` among them; the mmodes stage's
    ``n_samples`` summed over baselines): the ``f_k`` of the per-day jackknife
    (:func:`mmflow.imaging.jackknife.per_day_variance`) and of the day/night map
    (:func:`mmflow.imaging.jackknife.day_night_difference`). Flags count: a day half flagged has half
    the share of a whole one."""
    counts = np.asarray(counts, float)
    full = counts[list(names).index("full")]
    return {s: float(c / full) if full > 0 else 0.0 for s, c in zip(names, counts)}


def day_list(days):
    """``"day0 .. day2, day150 .. day152"``: the sidereal days present (runs of consecutive days joined)."""
    days = sorted(set(int(d) for d in days))
    runs, start = [], None
    for i, d in enumerate(days):
        start = d if start is None else start
        if i + 1 == len(days) or days[i + 1] != d + 1:
            runs.append(f"day{start}" if start == d else f"day{start} .. day{d}")
            start = None
    return ", ".join(runs)


def split_problems(names, lsts, days, sun_elevation, n_bins, min_coverage):
    """What is wrong with the time-subset splits among ``names`` for these data: ``[(name, problem, fix)]``.

    ``day<k>`` for a day the data do not hold (beyond them, or in a gap); per-day splits of less
    than two days; with any ``day<k>`` listed, EVERY day of the data that fills less than
    ``min_coverage`` of the ``n_bins`` sidereal bins (:func:`bin_coverage`), listed or not: the
    per-day jackknife's ``all = sum_k f_k day_k`` holds the partial day too, and a partial day's
    noise is not spread over the bins like the full data's, so the listed days' estimate is biased
    (1.5 days, ``[full, day0]``: sigma ~19 % low); ``day`` / ``night`` below ``min_coverage``.
    ``sun_elevation`` None: the ``day`` / ``night`` splits are not checked. Negative ``days``
    (integrations without an LST) are in no day.
    """
    lsts = np.asarray(lsts, float)
    days = np.asarray(days, int)
    present = sorted(set(np.unique(days[days >= 0]).tolist()))
    held = f"the data hold {len(present)} sidereal day{'s' if len(present) != 1 else ''} ({day_list(present)})"
    out = []
    listed = day_splits(names)
    if listed and len(present) < 2:
        out.append((listed[min(listed)], f"per-day splits of data spanning {len(present)} sidereal day: the one "
                    "day is the full data", "observe two or more sidereal days, or use mmode.splits=[full, even, odd]"))
        listed = {}
    for k, s in listed.items():
        if k not in present:
            out.append((s, f"{held}, no {s}", f"list only days the data hold in mmode.splits ({day_list(present)})"))
    if listed:
        for j in present:
            cov = bin_coverage(lsts[days == j], n_bins)
            if cov < min_coverage:
                out.append((f"day{j}", f"day{j} fills {cov:.1%} of the {n_bins} sidereal bins (need "
                            f"mmode.min_coverage = {min_coverage:g}): the per-day jackknife needs whole days",
                            "trim the data to whole sidereal days or use even/odd (mmode.splits=[full, even, odd])"))
    if sun_elevation is not None:
        for s, mask in split_masks([s for s in names if split_kind(s)[0] == "sun"], days, sun_elevation).items():
            cov = bin_coverage(lsts[mask], n_bins)
            if cov < min_coverage:
                out.append((s, f"the '{s}' integrations fill only {cov:.1%} of the {n_bins} sidereal bins (need "
                            f"mmode.min_coverage = {min_coverage:g}): over one day, or a few, each half of a day "
                            "sees only part of the LSTs", "day/night is a jackknife only with months of data (the "
                            "Sun's RA moves ~1 deg a day); remove day / night from mmode.splits"))
    return out
