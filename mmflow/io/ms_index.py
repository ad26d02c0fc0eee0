"""The plan's cheap pass over many MeasurementSets (one per integration, as the OVRO-LWA writes them).

pyuvdata's metadata read of a MeasurementSet costs as much as reading it whole (it opens every
subtable several times and computes apparent coordinates), so planning 768 single-integration
MS files with it would read every file twice. The plan therefore reads the first MS fully with
pyuvdata (every check of ``mmflow.io.checks``) and, for every other MS, only the columns the
plan needs, with python-casacore: the main table's ``TIME``, ``ANTENNA1``, ``ANTENNA2``,
``DATA_DESC_ID`` and the ``DATA`` unit, and the ``SPECTRAL_WINDOW``, ``ANTENNA`` and
``POLARIZATION`` subtables. Each file is then checked against the first (frequencies may
differ: subbands, grouped by the plan, :mod:`mmflow.io.channels`):
same antenna table (absolute positions within ``checks.POSITION_TOL_M``),
same correlation types (so pyuvdata gives it the same polarisation axis and Stokes-I recipe),
same units, one spectral window, no duplicated (time, baseline) row. Its phase centre, whatever
it is, is undone from the file's own ``UVW`` (:mod:`mmflow.io.ms_read`), as pyuvdata's
``unproject_phase`` does; a MeasurementSet is always phased. Times are converted as
pyuvdata converts them (``Time(TIME / 86400, format="mjd", scale=<the column's MEASINFO>).utc.jd``);
antenna numbers are ``ANTENNA1``/``ANTENNA2`` (pyuvdata's convention for MS).
``mmflow.io.ingest.index_agrees`` verifies both on the first file, and the plan falls back to
pyuvdata for every file if it does not.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from astropy.time import Time

from mmflow.errors import InputError
from mmflow.io import checks


@dataclass
class MSIndex:
    path: str
    time_mjd_s: np.ndarray
    time_scale: str
    ant_1_array: np.ndarray
    ant_2_array: np.ndarray
    n_ddid: int
    units: str
    freqs: np.ndarray
    antenna_positions: np.ndarray  # absolute ITRF (m), every row of the ANTENNA table
    corr_type: np.ndarray
    time_array: np.ndarray = None  # UTC JD, set by :func:`convert_times`


def read_index(path, compact=False):
    """The columns the plan needs from one MS (python-casacore; no data). ``compact`` is ignored: an
    MS's times are converted after the read (:func:`convert_times`); the OVRO-LWA's files are one
    integration each."""
    from casacore.tables import table  # deferred: optional (python-casacore)

    p = str(path).rstrip("/")
    with table(p, ack=False, readonly=True) as t:
        time = t.getcol("TIME")
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        n_ddid = len(np.unique(t.getcol("DATA_DESC_ID")))
        scale = str(t.getcolkeyword("TIME", "MEASINFO").get("Ref", "UTC"))
        units = t.getcolkeywords("DATA").get("QuantumUnits", "uncalib")
    units = units[0] if isinstance(units, (list, tuple)) else units
    with table(p + "/SPECTRAL_WINDOW", ack=False, readonly=True) as t:
        freqs = np.asarray(t.getcol("CHAN_FREQ"), float)
    with table(p + "/ANTENNA", ack=False, readonly=True) as t:
        pos = np.asarray(t.getcol("POSITION"), float)
    with table(p + "/POLARIZATION", ack=False, readonly=True) as t:
        corr = np.asarray(t.getcol("CORR_TYPE"))
    return MSIndex(p, np.asarray(time, float), scale, np.asarray(a1), np.asarray(a2), n_ddid, str(units), freqs,
                   pos, corr)


def ms_time_to_jd(time_mjd_s, scale):
    """An MS ``TIME`` column (MJD seconds in the column's ``MEASINFO`` scale) as UTC JD, as pyuvdata
    converts it: ``Time(TIME / 86400, format="mjd", scale=scale).utc.jd``."""
    return Time(np.asarray(time_mjd_s) / 86400.0, format="mjd", scale=str(scale).lower()).utc.jd


def convert_times(indices):
    """Set ``time_array`` (UTC JD) of every index as pyuvdata does, one astropy call per time scale."""
    for scale in {ix.time_scale for ix in indices}:
        group = [ix for ix in indices if ix.time_scale == scale]
        jd = ms_time_to_jd(np.concatenate([ix.time_mjd_s for ix in group]), scale)
        start = 0
        for ix in group:
            ix.time_array = jd[start:start + len(ix.time_mjd_s)]
            start += len(ix.time_mjd_s)


def check_against(indices, ref, ref_uv, info):
    """Check every MS index against the first file (``ref``, read and checked with pyuvdata)."""
    if info["phase"] != "phased":
        raise InputError(ref.path, "FIELD.PHASE_DIR", "pyuvdata reads the first MeasurementSet as unphased",
                         "ingest MeasurementSets with a phase centre (as every MS writer writes them)")
    for ix in indices:
        if ix.n_ddid != 1:
            raise InputError(ix.path, "DATA_DESC_ID", f"{ix.n_ddid} spectral windows / polarisation setups",
                             "split the MS by spectral window (one setup per run)")
        if not np.array_equal(ix.corr_type, ref.corr_type):
            raise InputError(ix.path, "POLARIZATION.CORR_TYPE", f"correlation types {ix.corr_type.ravel().tolist()} "
                             f"differ from {ref.path}'s {ref.corr_type.ravel().tolist()}",
                             "ingest files with one polarisation setup per run")
        if ix.units != ref.units:
            raise InputError(ix.path, "vis_units", f"unit {ix.units!r} differs from {ref.path}'s {ref.units!r}",
                             "ingest files in one unit per run")
        if ix.antenna_positions.shape != ref.antenna_positions.shape:
            raise InputError(ix.path, "antenna_numbers", f"antenna set differs from {ref.path}",
                             "ingest files from one array configuration per run")
        moved = np.linalg.norm(ix.antenna_positions - ref.antenna_positions, axis=1)
        if moved.max() > checks.POSITION_TOL_M:
            k = int(np.argmax(moved))
            raise InputError(ix.path, "antenna_positions", f"antenna {k} is {moved[k]:.3f} m from its position in "
                             f"{ref.path} (tolerance {checks.POSITION_TOL_M} m)",
                             "ingest files from one array survey per run (fix the antenna table)")
        checks.duplicate_rows(ix.time_array, ix.ant_1_array, ix.ant_2_array, ix.path)
