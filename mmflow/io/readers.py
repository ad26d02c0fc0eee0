"""Read one input file's kept polarisations (the per-file step of an ingest task).

:func:`read_metadata` reads a file's metadata with pyuvdata (no data). :func:`read_file`
returns a :class:`FileData`: each row's time, antennas, LST and the visibilities of the kept
polarisations (:mod:`mmflow.io.polarization`),
flags and sample counts, in Jy. A drift-scan UVH5 file whose metadata the plan has already
read and checked is read directly with h5py (its ``Data/visdata``, ``Data/flags``,
``Data/nsamples`` and the header's row arrays, as the UVH5 format defines them), so its
metadata are not parsed a second time. A MeasurementSet whose metadata the plan has checked is
read directly with python-casacore (:mod:`mmflow.io.ms_read`: the main table's columns,
pyuvdata's conjugation and unprojection reproduced bit for bit). Every other file (uvfits, files
read without a plan) goes through ``pyuvdata.UVData.read``, and phased data (any phase centre)
are unprojected exactly with ``UVData.unproject_phase``. The paths give the same numbers
(``tests/workflow/test_ingest_formats.py``). pyuvdata reads with astropy's site list kept offline
(:func:`mmflow.offline.offline_site_registry`): a telescope astropy does not know is placed
where the file's antennas are, never looked up on the network.
"""
from __future__ import annotations

import threading
from contextlib import nullcontext

import numpy as np

from mmflow.import_thread import import_in_thread
from mmflow.io import checks
from mmflow.io.file_data import FileData
from mmflow.io.ms_read import read_ms_direct
from mmflow.io.polarization import select_pols
from mmflow.offline import offline_site_registry

_CASACORE_LOCK = threading.Lock()  # casacore's table cache is not thread-safe

__all__ = ["FileData", "file_kind", "read_file", "read_metadata", "unflagged_nonfinite"]


def file_kind(path, fmt=None):
    """The kind of one input path: the forced format, "uvh5", "ms", or None (pyuvdata decides)."""
    if fmt is not None:
        return fmt
    p = str(path).lower().rstrip("/")
    if p.endswith((".uvh5", ".h5", ".hdf5")):
        return "uvh5"
    if p.endswith(".ms"):
        return "ms"
    return None


def _kwargs(path, fmt):
    """pyuvdata read arguments: the forced format, and single-channel MS spectral windows kept
    (pyuvdata drops them by default as "continuum" windows)."""
    kind = file_kind(path, fmt)
    kw = {} if fmt is None else {"file_type": fmt}
    if kind == "ms":
        kw["ignore_single_chan"] = False
    return kw, kind


def read_metadata(path, fmt=None):
    """pyuvdata ``UVData`` with metadata only. pyuvdata's own consistency check is skipped:
    mmflow checks what it uses (``mmflow.io.checks``)."""
    return _read_uvdata(path, fmt, read_data=False)


def _read_uvdata(path, fmt, **options):
    """One file read by pyuvdata (its own check skipped; a MeasurementSet under the casacore lock)."""
    import_in_thread("pyuvdata")  # its first import would pin this frame and its caller's locals (mmflow.import_thread)
    from pyuvdata import UVData  # deferred: pyuvdata takes 2-3.5 s to import (docs/performance.md)

    offline_site_registry()
    kw, kind = _kwargs(path, fmt)
    uv = UVData()
    with _CASACORE_LOCK if kind == "ms" else nullcontext():
        uv.read(str(path), run_check=False, **options, **kw)
    return uv


def read_file(path, fmt=None, info=None, site=None):
    """The kept polarisations (Jy) of one file: the Stokes-I hands, then their cross hands (``FileData.vis``'s
    last axis: ``info["pols"] + info["cross_pols"]``). ``info`` is the plan's ``checks.file_info`` for it
    (computed here from the file when None); ``site`` = ``(lat_deg, lon_deg, height_m)`` of the checked layout
    lets a MeasurementSet be read directly (its LSTs computed from its times there)."""
    kind = file_kind(path, fmt)
    if info is not None and info["phase"] == "drift" and kind == "uvh5":
        out = _read_uvh5_direct(path, _wanted(info, "indices"), len(info["pol_indices"]))
    elif info is not None and site is not None and kind == "ms":
        out = read_ms_direct(path, _wanted(info, "numbers"), info["phase"] == "phased", site, _CASACORE_LOCK,
                             len(info["pol_numbers"]))
    else:
        out, info = _read_pyuvdata(path, fmt, info)
    # the plan (or file_info in _read_pyuvdata) has checked the unit against calibrate.enabled
    scale = checks.unit_scale(info["vis_units"], out.freqs, path, calibrated_here=True) * info.get("pol_factor", 1.0)
    if np.any(scale != 1.0):
        out.vis = out.vis * scale[None, :, None]
    return out


def unflagged_nonfinite(path, fmt, info, site):
    """``(n, size)``: the unflagged NaN/inf samples among the ``size`` samples an ingest task keeps of one
    file (:func:`read_file`'s polarisations and rows), or None where the file has no direct read (uvfits:
    its ingest task checks it). UVH5 files (any phase state) are read with h5py and MeasurementSets with
    python-casacore, without pyuvdata; the unit scale and the unprojection are finite factors, so they
    are not needed to tell whether a sample is finite."""
    kind = file_kind(path, fmt)
    if kind == "uvh5":  # in blocks of rows: the driver's memory stays bounded whatever the file's size
        pols = _wanted(info, "indices")
        parts = (_read_uvh5_direct(path, pols, len(info["pol_indices"]), rows) for rows in _row_blocks(path, len(pols)))
    elif kind == "ms" and site is not None:
        parts = [read_ms_direct(path, _wanted(info, "numbers"), False, site, _CASACORE_LOCK, len(info["pol_numbers"]))]
    else:
        return None
    n = size = 0
    for out in parts:
        n += int(np.count_nonzero(~np.isfinite(out.vis) & ~out.flags))
        size += int(out.vis.size)
    return n, size


#: bytes of visibilities (complex128) :func:`unflagged_nonfinite` holds at a time of a UVH5 file
SCAN_BLOCK_BYTES = 1 << 28


def _row_blocks(path, n_pols):
    """Slices of a UVH5 file's rows holding about :data:`SCAN_BLOCK_BYTES` of ``n_pols`` polarisations."""
    import h5py  # deferred: as in _read_uvh5_direct

    with h5py.File(str(path), "r") as f:
        shape = f["Data"]["visdata"].shape
    per_row = max(1, int(np.prod(shape[1:-1])) * n_pols * 16)
    step = max(1, SCAN_BLOCK_BYTES // per_row)
    return [slice(r, r + step) for r in range(0, shape[0], step)]


def _wanted(info, what):
    """The polarisations to read: the Stokes-I hands, then the cross hands (``what``: "indices" along
    pyuvdata's axis or pyuvdata "numbers")."""
    return list(info[f"pol_{what}"]) + list(info.get(f"cross_{what}", []))


def _read_pyuvdata(path, fmt, info):
    uv = _read_uvdata(path, fmt)
    if info is None:
        info = checks.file_info(uv, str(path))
    if info["phase"] == "phased":
        uv.unproject_phase()
    vis, flags, nsample = select_pols(np.asarray(uv.data_array), np.asarray(uv.flag_array),
                                      np.asarray(uv.nsample_array), _wanted(info, "indices"))
    raw = FileData(np.asarray(uv.time_array), np.asarray(uv.ant_1_array), np.asarray(uv.ant_2_array),
               np.asarray(uv.lst_array), vis, flags, nsample, np.asarray(uv.freq_array, float).ravel())
    return raw, info


def _read_uvh5_direct(path, pol_indices, n_parallel, rows=slice(None)):
    """The UVH5 datasets themselves (format: pyuvdata docs, "UVH5 file format"): rows in file
    order (``rows``: a slice of them; default all), ``visdata`` (Nblts, [1,] Nfreqs, Npols), complex
    or an integer ``r``/``i`` compound.
    Autocorrelations' parallel hands (the first ``n_parallel`` of ``pol_indices``) are made real,
    as pyuvdata's ``fix_autos`` does on read."""
    import h5py  # deferred: h5py comes with pyuvdata (not a direct dependency), uvh5 files only

    with h5py.File(str(path), "r") as f:
        h, d = f["Header"], f["Data"]
        time_jd = h["time_array"][rows]
        ant1, ant2 = h["ant_1_array"][rows], h["ant_2_array"][rows]
        lst = h["lst_array"][rows]
        freqs = np.asarray(h["freq_array"][()], float).ravel()
        pols = list(pol_indices)
        lo, hi = min(pols), max(pols) + 1  # read the contiguous polarisation slab holding them
        data = d["visdata"]
        squeeze = data.ndim == 4
        sl = (rows, 0, slice(None), slice(lo, hi)) if squeeze else (rows, slice(None), slice(lo, hi))
        vis = data[sl]
        if vis.dtype.names:
            vis = vis["r"].astype(np.float64) + 1j * vis["i"].astype(np.float64)
        flags, nsample = d["flags"][sl], d["nsamples"][sl]
    idx = [p - lo for p in pols]
    vis, flags, nsample = select_pols(vis, flags, nsample, idx)
    auto = ant1 == ant2
    if auto.any():
        vis[auto, :, :n_parallel] = vis[auto, :, :n_parallel].real
    return FileData(time_jd, ant1, ant2, lst, vis, flags, nsample, freqs)
