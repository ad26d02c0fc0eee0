"""The plan's cheap pass over many UVH5 files (one per integration, or per block of integrations).

pyuvdata's metadata read of a UVH5 file parses and validates its whole header (docs/performance.md),
as much as the data read of a single-integration file. The plan therefore reads the first file
with pyuvdata (every check of ``mmflow.io.checks``) and, for every other file, only the header
datasets it needs with h5py (the UVH5 format's ``Header``: ``time_array``, ``ant_1_array``,
``ant_2_array``, ``freq_array``, ``polarization_array``, ``vis_units``, ``antenna_numbers``,
``antenna_positions``, ``latitude``/``longitude``/``altitude`` and the ``phase_center_catalog``'s
``cat_type``), then checks each against the first (frequencies may differ: subbands, grouped
by the plan): polarisations (so the same Stokes-I recipe), units and antenna numbers; absolute antenna positions
and site within
``checks.POSITION_TOL_M``; drift-scan (``unprojected``) data only; no duplicated (time, baseline)
row. Times and antenna numbers are the header's own (pyuvdata reads them as they are);
``mmflow.io.ingest.index_agrees`` verifies that on the first file.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmflow.errors import InputError
from mmflow.io import checks


@dataclass
class UVH5Index:
    path: str
    time_array: np.ndarray
    ant_1_array: np.ndarray
    ant_2_array: np.ndarray
    freqs: np.ndarray
    pols: np.ndarray
    units: str
    antenna_numbers: np.ndarray
    antenna_positions: np.ndarray  # relative to the site (m, ECEF axes)
    lat_lon_alt: np.ndarray  # deg, deg, m
    cat_types: list
    compact: bool = False  # rows reduced to the distinct times and antenna pairs (duplicates refused)


def _str(x):
    return x.decode() if isinstance(x, bytes) else str(x)


def read_index(path, compact=False):
    """The header datasets the plan needs from one UVH5 file (h5py; no data).

    ``compact``: refuse duplicated (time, baseline) rows now and keep only the file's distinct
    times and antenna pairs (what the plan uses of every file but the first): a file of 256
    integrations of 32,896 baselines holds 200 MB of row times and antenna numbers, 26 such
    files 5 GB on the driver; compacted, 0.5 MB each.
    """
    import h5py  # deferred: h5py comes with pyuvdata (not a direct dependency), uvh5 files only

    with h5py.File(str(path), "r") as f:
        h = f["Header"]
        if "phase_center_catalog" not in h:
            raise KeyError("no Header/phase_center_catalog (a pre-3.0 UVH5 file)")
        cat = h["phase_center_catalog"]
        rows = h["time_array"][()], h["ant_1_array"][()], h["ant_2_array"][()]
        if compact:
            rows = checks.distinct_rows(*rows, str(path))
        return UVH5Index(
            str(path), *rows,
            np.asarray(h["freq_array"][()], float).ravel(), h["polarization_array"][()], _str(h["vis_units"][()]),
            h["antenna_numbers"][()], np.asarray(h["antenna_positions"][()], float),
            np.array([h["latitude"][()], h["longitude"][()], h["altitude"][()]], float),
            [_str(cat[k]["cat_type"][()]) for k in cat], compact)


def convert_times(indices):
    """UVH5 stores UTC JD: nothing to convert (the MS index's interface)."""


def _ecef(lat_lon_alt):
    from pyuvdata.utils import XYZ_from_LatLonAlt  # deferred: pyuvdata takes 2-3.5 s to import (docs/performance.md)

    lla = np.atleast_2d(lat_lon_alt)
    return np.atleast_2d(XYZ_from_LatLonAlt(np.deg2rad(lla[:, 0]), np.deg2rad(lla[:, 1]), lla[:, 2]))


def check_against(indices, ref, ref_uv, info):
    """Check every UVH5 index against the first file (``ref``, read and checked with pyuvdata)."""
    if info["phase"] != "drift":
        raise InputError(ref.path, "phase_center_catalog", "the first file is not a drift scan",
                         "unproject to drift with pyuvdata: uv.unproject_phase()")
    sites = _ecef(np.array([ix.lat_lon_alt for ix in indices])) if indices else np.zeros((0, 3))
    ref_site = _ecef(ref.lat_lon_alt)[0]
    for ix, site in zip(indices, sites):
        if not np.array_equal(ix.pols, ref.pols):
            raise InputError(ix.path, "polarization_array", f"polarisations {ix.pols.tolist()} differ from "
                             f"{ref.path}'s {ref.pols.tolist()}", "ingest files with one polarisation setup per run")
        if ix.units != ref.units:
            raise InputError(ix.path, "vis_units", f"unit {ix.units!r} differs from {ref.path}'s {ref.units!r}",
                             "ingest files in one unit per run")
        if not np.array_equal(ix.antenna_numbers, ref.antenna_numbers):
            raise InputError(ix.path, "antenna_numbers", f"antenna set differs from {ref.path}",
                             "ingest files from one array configuration per run")
        dloc = float(np.linalg.norm(site - ref_site))
        if dloc > checks.POSITION_TOL_M:
            raise InputError(ix.path, "telescope.location", f"the site is {dloc:.3f} m from {ref.path}'s "
                             f"(tolerance {checks.POSITION_TOL_M} m)",
                             "ingest files from one site and one array survey per run")
        moved = np.linalg.norm(ix.antenna_positions + site - ref.antenna_positions - ref_site, axis=1)
        if moved.max() > checks.POSITION_TOL_M:
            k = int(np.argmax(moved))
            raise InputError(ix.path, "antenna_positions", f"antenna {int(ix.antenna_numbers[k])} is {moved[k]:.3f} m "
                             f"from its position in {ref.path} (tolerance {checks.POSITION_TOL_M} m)",
                             "ingest files from one array survey per run (fix the antenna table)")
        if any(t != "unprojected" for t in ix.cat_types):
            raise InputError(ix.path, f"phase_center_catalog (cat_type={','.join(sorted(set(ix.cat_types)))})",
                             "the data are phased, not a drift scan like the first file",
                             "unproject to drift with pyuvdata 3.x: uv = UVData.from_file(f); uv.unproject_phase(); "
                             "uv.write_uvh5(out)")
        if not ix.compact:
            checks.duplicate_rows(ix.time_array, ix.ant_1_array, ix.ant_2_array, ix.path)
