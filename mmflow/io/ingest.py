"""Ingest drift-scan data from any format pyuvdata reads (UVH5, uvfits, MeasurementSet).

The plan (metadata of every file, read once by the driver without data) checks that files
agree on frequencies and antennas, orders integrations by time, rejects duplicate times, and
stores each row's time and file in ``vis.zarr``. Each task then reads only the files covering
its time chunk; no worker rescans the glob. Stokes I = (XX + YY) / 2 (paper section 2); a single polarisation is used as is.
pyuvdata's data (``V_12 = <E_1 E_2*>``, ``b = x_2 - x_1``, as simulated by matvis and hera_sim)
follow the same ``exp(+2 pi i b.r)`` sign as mmflow, which ``tests/test_ingest.py`` checks by
imaging a matvis drift scan: sources land at their ICRS positions. ``input.conjugate``
flips the sign for data written in the opposite convention.
"""
from __future__ import annotations

import glob as globmod
import logging
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from mmflow.errors import InputError
from mmflow.telescope.layout import Layout

log = logging.getLogger("mmflow.ingest")


@dataclass
class IngestPlan:
    files: list
    row_time: np.ndarray  # (n_time,) UTC JD of each row, ascending
    row_file: np.ndarray  # (n_time,) index into ``files`` of the file holding each row
    n_time: int
    freqs_hz: np.ndarray
    pairs: np.ndarray
    ant_numbers: np.ndarray
    layout: Layout
    epoch_jd: float
    integration_s: float
    skipped: list = field(default_factory=list)


def _read(path, fmt, read_data=True, times=None):
    from pyuvdata import UVData

    uv = UVData()
    kw = {} if fmt is None else {"file_type": fmt}
    if times is not None:
        kw["times"] = times
    uv.read(path, read_data=read_data, **kw)
    return uv


def plan_ingest(cfg):
    return _plan(cfg.input.path, cfg.input.format, cfg.input.on_bad_file)


@lru_cache(maxsize=4)
def _plan(pattern, fmt, on_bad):
    if not pattern:
        raise InputError("workflow", "input.path", "no input path", "set input.path=/data/*.uvh5")
    files = sorted(globmod.glob(pattern)) or ([pattern] if "*" not in pattern else [])
    if not files:
        raise InputError(pattern, "input.path", "no files match", "check the path or glob")
    metas, good, skipped = [], [], []
    for f in files:
        try:
            metas.append(_read(f, fmt, read_data=False))
            good.append(f)
        except Exception as exc:  # pyuvdata raises many exception types for corrupt files
            msg = f"{f}: unreadable ({type(exc).__name__}: {exc})"
            if on_bad == "skip":
                log.warning("skipping %s", msg)
                skipped.append(msg)
                continue
            raise InputError(f, "file", f"pyuvdata cannot read it ({exc})",
                             "remove or replace the file, or set input.on_bad_file=skip") from exc
    ref = metas[0]
    freqs = np.asarray(ref.freq_array).ravel()
    ants = np.asarray(ref.telescope.antenna_numbers)
    for f, uv in zip(good[1:], metas[1:]):
        if not np.allclose(np.asarray(uv.freq_array).ravel(), freqs):
            raise InputError(f, "freq_array", f"frequencies differ from {good[0]}",
                             "ingest one spectral setup per run (select channels first)")
        if not np.array_equal(np.asarray(uv.telescope.antenna_numbers), ants):
            raise InputError(f, "antenna_numbers", f"antenna set differs from {good[0]}",
                             "ingest files from one array configuration per run")
    # baselines: the union over files as (i, j) antenna-index pairs with i <= j; a baseline a
    # file lacks is simply unmeasured (weight 0) in that file's integrations
    index = {int(a): k for k, a in enumerate(ants)}
    found = []
    for uv in metas:
        a1 = [index[int(x)] for x in np.asarray(uv.ant_1_array)]
        a2 = [index[int(x)] for x in np.asarray(uv.ant_2_array)]
        found.append(np.sort(np.stack([a1, a2], 1), 1))
    pairs = np.unique(np.concatenate(found), axis=0)
    seen = {}
    all_t = []
    for fi, uv in enumerate(metas):
        for t in np.unique(np.asarray(uv.time_array)):
            key = round(float(t) * 86400.0, 3)
            if key in seen:
                raise InputError(good[fi], "time_array", f"integration at JD {t:.6f} also in {good[seen[key]]}",
                                 "remove duplicated files or integrations")
            seen[key] = fi
            all_t.append((float(t), fi))
    all_t.sort()
    enu = _antenna_enu(ref)
    lat, lon, alt = ref.telescope.location_lat_lon_alt_degrees
    layout = Layout([str(n) for n in ref.telescope.antenna_names], enu, float(lat), float(lon), float(alt),
                    provenance=f"ingested from {good[0]}")
    tint = float(np.median(np.asarray(ref.integration_time)))
    times = np.array([t for t, _ in all_t])
    return IngestPlan(good, times, np.array([fi for _, fi in all_t]), len(all_t), freqs, pairs, ants, layout,
                      float(np.median(times)), tint, skipped)


def write_plan(group, plan):
    """Store what tasks need (row times, each row's file, antenna numbers) so no worker rescans files."""
    if "plan_time_jd" not in group:
        group.create_array("plan_time_jd", data=plan.row_time)
        group.create_array("plan_file", data=plan.row_file.astype("int32"))
        group.create_array("antenna_numbers", data=np.asarray(plan.ant_numbers, "int64"))


def _antenna_enu(uv):
    from pyuvdata.utils import ENU_from_ECEF

    ecef = np.asarray(uv.telescope.antenna_positions) + np.asarray(uv.telescope._location.xyz())
    return ENU_from_ECEF(ecef, center_loc=uv.telescope.location)


def stokes_i(uv):
    """(XX + YY) / 2 from a UVData (or the single polarisation present); returns data, flags."""
    pols = list(uv.get_pols())
    data = np.asarray(uv.data_array)  # (nblt, nfreq, npol)
    flags = np.asarray(uv.flag_array)
    if "xx" in pols and "yy" in pols:
        ix, iy = pols.index("xx"), pols.index("yy")
        return 0.5 * (data[..., ix] + data[..., iy]), flags[..., ix] | flags[..., iy]
    if "pI" in pols:
        i = pols.index("pI")
        return data[..., i], flags[..., i]
    if len(pols) == 1:
        return data[..., 0], flags[..., 0]
    raise InputError("ingest", "polarization_array", f"cannot form Stokes I from {pols}",
                     "provide xx and yy (or a single polarisation)")


def _time_key(jd):
    return np.round(np.asarray(jd, float) * 86400.0, 3)


def ingest_time_chunk(cfg, store_path, row0, row1):
    """Read the files holding rows ``row0..row1`` (from the plan in the store) and write those rows."""
    import zarr

    g = zarr.open_group(str(store_path), mode="r+")
    files = g.attrs["files"]
    row_time = g["plan_time_jd"][row0:row1]
    row_file = g["plan_file"][row0:row1]
    pairs, ant_numbers = g["pairs"][:], g["antenna_numbers"][:]
    n, nbl, nf = len(row_time), len(pairs), g["freqs_hz"].shape[0]
    row_of = {k: r for r, k in enumerate(_time_key(row_time))}
    vis = np.zeros((n, nbl, nf), np.complex64)
    wts = np.zeros((n, nbl, nf), np.float32)
    lst = np.full(n, np.nan)
    pair_index = {(int(i), int(j)): k for k, (i, j) in enumerate(pairs)}
    index = {int(a): k for k, a in enumerate(ant_numbers)}
    for fi in np.unique(row_file):
        uv = _read(files[fi], cfg.input.format)
        data, flags = stokes_i(uv)
        nsamp = np.asarray(uv.nsample_array)[..., 0]
        keys, l_arr = _time_key(uv.time_array), np.asarray(uv.lst_array)
        a1 = np.array([index[int(x)] for x in uv.ant_1_array])
        a2 = np.array([index[int(x)] for x in uv.ant_2_array])
        for k in range(len(keys)):
            r = row_of.get(keys[k])
            if r is None:  # an integration of this file that belongs to another chunk
                continue
            i, j = int(a1[k]), int(a2[k])
            v = data[k]
            if i > j:  # V(j, i) = conj(V(i, j))
                i, j, v = j, i, np.conj(v)
            if cfg.input.conjugate:
                v = np.conj(v)
            b = pair_index[(i, j)]
            vis[r, b] = v
            wts[r, b] = np.where(flags[k], 0.0, nsamp[k])
            lst[r] = l_arr[k]
    g["vis"][row0:row0 + n] = vis
    g["weights"][row0:row0 + n] = wts
    g["lst"][row0:row0 + n] = lst
    g["time_jd"][row0:row0 + n] = row_time
    flagged = int(np.sum(np.all(wts == 0, axis=(1, 2))))
    return {"integrations": int(n), "fully_flagged_integrations": flagged, "files_read": int(len(np.unique(row_file)))}
