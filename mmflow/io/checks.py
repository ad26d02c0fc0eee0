"""Metadata and data checks made at ingest: what mmflow must not trust in an input file.

Each check either accepts, converts where the conversion is exact, or raises
:class:`mmflow.errors.InputError` naming the file, the field and the fix. They work on
plain arrays and pyuvdata ``UVData`` metadata (no data needed), so the plan runs them once per
file before anything is written.
"""
from __future__ import annotations

import logging

import numpy as np

from mmflow.errors import InputError
from mmflow.io.polarization import cross_recipe, stokes_i_recipe, stored_names
from mmflow.sky.units import jy_per_sr_per_kelvin

log = logging.getLogger("mmflow.ingest")

#: antenna positions (absolute ECEF) and the telescope location must agree across files to this.
POSITION_TOL_M = 0.01
#: phase-centre types pyuvdata's ``unproject_phase`` undoes exactly (it uses only each row's ``w``).
PROJECTED = ("sidereal", "ephem", "driftscan")


def phase_state(uv, what):
    """``"drift"`` for unprojected data, ``"phased"`` for data phased to any sidereal (or ephemeris,
    or fixed az/el) phase centre, one or many integrations per file; otherwise an error.

    Phased rows are unprojected exactly as pyuvdata's ``UVData.unproject_phase`` does:
    ``V_drift = V exp(-2 pi i (0 - w) nu / c)`` with ``w`` the row's ``uvw_array[:, 2]`` (the
    projection towards the phase centre), whatever the centre: the phase centre itself is not
    needed, only the file's ``w``.
    """
    cat = uv.phase_center_catalog or {}
    ids = np.unique(np.asarray(uv.phase_center_id_array)) if uv.phase_center_id_array is not None else []
    types = {int(i): cat[int(i)]["cat_type"] for i in ids if int(i) in cat}
    if all(t == "unprojected" for t in types.values()):
        return "drift"
    other = sorted({t for t in types.values() if t not in PROJECTED + ("unprojected",)})
    if other:
        raise InputError(what, f"phase_center_catalog (cat_type={','.join(other)})",
                         f"phase centres of type {other} are not undone by a w projection alone",
                         "unproject to drift with pyuvdata 3.x: uv = UVData.from_file(f); uv.unproject_phase(); "
                         "uv.write_uvh5(out)")
    return "phased"


def unit_scale(units, freqs, what, calibrated_here=False):
    """Factor per frequency that takes visibilities in ``units`` (pyuvdata ``vis_units``) to Jy.

    ``Jy``: 1. ``K str`` (Rayleigh-Jeans brightness temperature times solid angle):
    ``2 k nu^2 / c^2 / 1e-26`` Jy per K sr, exact. ``uncalib`` or any other unit: 1 (kept as
    they are) when ``calibrated_here`` (``calibrate.enabled``: the gains solved against the
    calibration sky model in Jy set the flux scale), else an error naming ``calibrate.enabled``.
    """
    units = str(units)
    freqs = np.asarray(freqs, float).ravel()
    if units == "Jy":
        return np.ones_like(freqs)
    if units == "K str":
        return jy_per_sr_per_kelvin(freqs)
    if calibrated_here:
        return np.ones_like(freqs)
    what_units = "uncalibrated ('uncalib')" if units == "uncalib" else f"in an unknown unit ({units!r})"
    raise InputError(what, "vis_units", f"the visibilities are {what_units}; without calibration mmflow needs Jy "
                     "(or 'K str')", "set calibrate.enabled=true (the gains, solved against calibrate.sources, set "
                     "the flux scale), or give data calibrated to Jy")


def antenna_ecef(uv):
    """Absolute ECEF (m) of every antenna, keyed by antenna number."""
    pos = np.asarray(uv.telescope.antenna_positions, float) + np.asarray(uv.telescope._location.xyz())
    return {int(n): p for n, p in zip(uv.telescope.antenna_numbers, pos)}


def compare_telescope(uv, ref, what, ref_what):
    """Antenna numbers, absolute antenna positions and the site agree with the reference file."""
    if not np.array_equal(np.asarray(uv.telescope.antenna_numbers), np.asarray(ref.telescope.antenna_numbers)):
        raise InputError(what, "antenna_numbers", f"antenna set differs from {ref_what}",
                         "ingest files from one array configuration per run")
    dloc = float(np.linalg.norm(np.asarray(uv.telescope._location.xyz()) - np.asarray(ref.telescope._location.xyz())))
    if dloc > POSITION_TOL_M:
        raise InputError(what, "telescope.location", f"the site is {dloc:.3f} m from {ref_what}'s "
                         f"(tolerance {POSITION_TOL_M} m)", "ingest files from one site and one array survey per run")
    a, b = antenna_ecef(uv), antenna_ecef(ref)
    moved = {n: float(np.linalg.norm(a[n] - b[n])) for n in a}
    worst = max(moved, key=moved.get)
    if moved[worst] > POSITION_TOL_M:
        raise InputError(what, "antenna_positions", f"antenna {worst} is {moved[worst]:.3f} m from its position in "
                         f"{ref_what} (tolerance {POSITION_TOL_M} m)",
                         "ingest files from one array survey per run (fix the antenna table)")


def time_key(jd):
    """Integration identity: the time rounded to the millisecond."""
    return np.round(np.asarray(jd, float) * 86400.0, 3)


def distinct_pairs(ant1, ant2):
    """The distinct ``(ant1, ant2)`` rows, sorted: one int64 key per row (np.unique over rows of a
    two-column array takes seconds at 8.4M rows)."""
    a1, a2 = np.asarray(ant1, np.int64), np.asarray(ant2, np.int64)
    if not len(a1):
        return a1, a2
    base = int(min(a1.min(), a2.min()))
    n = int(max(a1.max(), a2.max())) - base + 1
    keys = np.unique((a1 - base) * n + (a2 - base))
    return keys // n + base, keys % n + base


def _grid_block(tk, ant1, ant2):
    """The rows per integration when the rows are pyuvdata's regular grid (``time_axis_faster_than_bls=False``):
    blocks of one integration each (time keys ``tk``), every block the same ``(ant1, ant2)`` in the same
    order, distinct times, no baseline twice in a block (``(i, j)`` and ``(j, i)`` alike). Then no row
    repeats, shown in O(rows) without a sort. 0 when they are not."""
    n = len(tk)
    if not n:
        return 0
    starts = np.flatnonzero(np.r_[True, tk[1:] != tk[:-1]])
    nb = n // len(starts)
    if nb * len(starts) != n or not np.array_equal(starts, np.arange(0, n, nb)):
        return 0
    b1, b2 = ant1.reshape(-1, nb), ant2.reshape(-1, nb)
    if not ((b1 == b1[0]).all() and (b2 == b2[0]).all()):
        return 0
    first = np.sort(np.stack([b1[0], b2[0]], 1), 1)
    ok = len(np.unique(tk[starts])) == len(starts) and len(distinct_pairs(*first.T)[0]) == nb
    return nb if ok else 0


def _refuse_repeats(jd, tk, ant1, ant2, what):
    lo, hi = np.minimum(ant1, ant2), np.maximum(ant1, ant2)
    if not len(lo):
        return
    _, t_idx = np.unique(tk, return_inverse=True)
    base = int(lo.min())
    n = int(hi.max()) - base + 1  # one int64 key per row, (time index, i, j): 8.4M rows sort in ~1 s
    keys = (t_idx.astype(np.int64) * n + (lo - base)) * n + (hi - base)
    order = np.argsort(keys, kind="stable")
    same = np.flatnonzero(keys[order][1:] == keys[order][:-1])
    if len(same):
        r1, r2 = int(order[same[0]]), int(order[same[0] + 1])
        raise InputError(what, "time_array/ant_1_array/ant_2_array",
                         f"{len(same)} duplicated (time, baseline) rows: rows {r1} and {r2} are both baseline "
                         f"({int(lo[r1])}, {int(hi[r1])}) at JD {float(jd[r1]):.6f}",
                         "remove the duplicated rows (pyuvdata: uv.select(blt_inds=...)) or the duplicated file")


def duplicate_rows(jd, ant1, ant2, what):
    """Refuse two rows of one file with the same (time, baseline), (i, j) and (j, i) alike."""
    tk = time_key(jd)
    if not _grid_block(tk, ant1, ant2):
        _refuse_repeats(jd, tk, ant1, ant2, what)


def distinct_rows(jd, ant1, ant2, what):
    """Refuse repeated rows (:func:`duplicate_rows`), and return the file's distinct times (sorted) and
    distinct ``(ant1, ant2)`` pairs (:func:`distinct_pairs`): read off the first integration's block
    for pyuvdata's regular grid, from every row otherwise."""
    tk = time_key(jd)
    nb = _grid_block(tk, ant1, ant2)
    if nb:
        return np.sort(jd[::nb]), *distinct_pairs(ant1[:nb], ant2[:nb])
    _refuse_repeats(jd, tk, ant1, ant2, what)
    return np.unique(jd), *distinct_pairs(ant1, ant2)


def nonfinite(vis, flagged, what, mode):
    """Unflagged NaN / inf samples: ``mode="error"`` refuses the file naming the count;
    ``mode="flag"`` returns a mask of them to flag (the caller counts and logs them)."""
    bad = ~np.isfinite(vis) & ~flagged
    n = int(np.count_nonzero(bad))
    if n and mode != "flag":
        raise nonfinite_error(what, n, vis.size)
    if n:
        log.warning("%s: flagged %d unflagged NaN/inf samples (input.nonfinite=flag)", what, n)
    return bad, n


def nonfinite_error(what, n, size, others=()):
    """The :class:`InputError` for ``n`` unflagged NaN/inf samples (of ``size``) in the file ``what``;
    ``others``: ``(file, n)`` of further files with them, named in the same message."""
    more = ""
    if others:
        shown = ", ".join(f"{f} ({k})" for f, k in others[:3])
        more = f"; so are samples of {len(others)} more file(s): {shown}" + (", ..." if len(others) > 3 else "")
    return InputError(what, "data_array", f"{n} unflagged samples are NaN or inf (of {size}){more}",
                      "flag them in the file, or set input.nonfinite=flag to flag them at ingest (counted and "
                      "logged)")


def file_info(uv, what, calibrated_here=False):
    """Check one file's metadata; return what a task needs to make Stokes I in Jy from it:
    ``{"phase": "drift"|"phased", "vis_units": ..., "pol_indices": [...], "pol_numbers": [-5, -6],
    "pols": ['xx', 'yy'], "cross_indices", "cross_numbers", "cross_pols": ['xy', 'yx']}`` (indices along
    pyuvdata's polarisation axis, and their pyuvdata numbers; the cross hands of a parallel pair,
    :func:`mmflow.io.polarization.cross_recipe`)
    (``calibrated_here``: see :func:`unit_scale`)."""
    indices, single = stokes_i_recipe(uv.polarization_array, what)
    if single:
        log.info("%s: one parallel-hand polarisation stands in for Stokes I", what)
    unit_scale(uv.vis_units, uv.freq_array, what, calibrated_here)
    duplicate_rows(np.asarray(uv.time_array), np.asarray(uv.ant_1_array), np.asarray(uv.ant_2_array), what)
    cross = cross_recipe(uv.polarization_array, indices)
    conv = getattr(uv, "pol_convention", None)
    return {"phase": phase_state(uv, what), "vis_units": str(uv.vis_units), "pol_indices": [int(i) for i in indices],
            "pol_convention": None if conv is None else str(conv),
            "pol_numbers": [int(uv.polarization_array[i]) for i in indices],
            "pols": stored_names(uv.polarization_array, indices), "cross_indices": [int(i) for i in cross],
            "cross_numbers": [int(uv.polarization_array[i]) for i in cross],
            "cross_pols": stored_names(uv.polarization_array, cross)}
