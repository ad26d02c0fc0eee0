"""Ingest drift-scan data from any format pyuvdata reads (UVH5, uvfits, MeasurementSet).

The plan reads every file's metadata once (no data): with pyuvdata, files read concurrently,
or, for many UVH5 / MS files, pyuvdata for the first and only the header datasets / columns it
needs for the rest (``mmflow.io.uvh5_index``, ``mmflow.io.ms_index``). It checks them (``mmflow.io.checks``: same
frequencies, antenna numbers, antenna positions and
site; drift or zenith-phased data; units Jy or K sr; no duplicated (time, baseline) row inside a
file or integration across files; a polarisation set that holds Stokes I), orders integrations
by time and stores each row's time and file in ``vis.zarr`` with what each task needs per file
(phase state, units, the polarisations that make Stokes I). Each task then reads only the
files covering its time chunk (concurrently, ``mmflow.io.readers``), refuses (or, with
``input.nonfinite=flag``, flags and counts) unflagged NaN/inf samples before it writes, and
writes its rows. No worker rescans the glob.

Polarisations: ``mmflow.io.polarization`` keeps those that make Stokes I (I; XX and YY; RR and
LL; or one parallel hand), chosen by pyuvdata polarisation number so that ``ee``/``nn``
labels are XX/YY, as ``vis.zarr``'s ``pol`` axis: calibration acts per hand, and Stokes I is
formed where the corrected data are next read.
pyuvdata's data (``V_12 = <E_1 E_2*>``, ``b = x_2 - x_1``, as simulated by matvis and hera_sim)
follow the same ``exp(+2 pi i b.r)`` sign as mmflow, which ``tests/workflow/test_ingest.py`` checks by
imaging a matvis drift scan: sources land at their ICRS positions. ``input.conjugate``
flips the sign for data written in the opposite convention.
"""
from __future__ import annotations

import glob as globmod
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import zarr

from mmflow.errors import InputError
from mmflow.io import checks, ms_index, uvh5_index
from mmflow.io.channels import average_channels, frequency_sets, select_channels
from mmflow.io.polarization import pol_factor
from mmflow.io.readers import file_kind, read_file, read_metadata, unflagged_nonfinite
from mmflow.io.run_stores import STORES
from mmflow.mmode.transform import bin_coverage
from mmflow.sky.frames import apparent_sidereal_time
from mmflow.telescope.layout import Layout
from mmflow.threads import n_threads

log = logging.getLogger("mmflow.ingest")


@dataclass
class IngestPlan:
    files: list
    row_time: np.ndarray  # (n_time,) UTC JD of each row, ascending
    file_rows: np.ndarray  # (n_file, 2) first and last row (inclusive) of each file's integrations
    n_time: int
    freqs_hz: np.ndarray  # (n_out,) the kept (averaged) channels' frequencies
    channel_width_hz: float  # the kept channels' width (file channel width x input.average_channels)
    pairs: np.ndarray
    ant_numbers: np.ndarray
    layout: Layout
    epoch_jd: float
    integration_s: float
    skipped: list = field(default_factory=list)
    file_info: list = field(default_factory=list)  # per file: checks.file_info + "out" / "blocks" (its channels)

    @property
    def pols(self):
        """The polarisations kept (``vis.zarr``'s ``pol`` axis): the same for every file."""
        return self.file_info[0]["pols"]

    @property
    def cross_pols(self):
        """The cross hands carried beside them (``vis.zarr``'s ``vis_cross``; ``[]`` when none)."""
        return self.file_info[0].get("cross_pols", [])


#: endings of the files (or MeasurementSet directories) pyuvdata reads, for a directory given as input.path
DATA_SUFFIXES = (".uvh5", ".h5", ".hdf5", ".uvfits", ".fits", ".ms")


def _files(pattern):
    if not pattern:
        raise InputError("workflow", "input.path", "no input path", "set input.path=/data/*.uvh5")
    files = sorted(globmod.glob(pattern)) or ([pattern] if "*" not in pattern else [])
    if not files:
        raise InputError(pattern, "input.path", "no files match", "check the path or glob")
    if len(files) == 1:
        _refuse_plain_directory(files[0])
    return files


def _refuse_plain_directory(path):
    """A directory given as ``input.path`` that is not a data set itself (a MeasurementSet's
    ``table.dat``, a Miriad ``visdata``): refused naming what it holds, with the glob to give."""
    p = Path(path)
    if not p.is_dir() or (p / "table.dat").exists() or (p / "visdata").exists():
        return
    found = sorted(q.suffix.lower() for q in p.iterdir() if q.suffix.lower() in DATA_SUFFIXES)
    if not found:
        raise InputError(str(p), "input.path", f"no data files in {p} (a directory with no "
                         f"{' / '.join(DATA_SUFFIXES)} file in it)",
                         "point input.path at the data: a file, or a glob such as '/data/day/*.uvh5'")
    common = max(set(found), key=found.count)
    raise InputError(str(p), "input.path", f"a directory of {len(found)} data files, not a data file itself",
                     f"give a glob of its files: input.path='{p / ('*' + common)}'")


def _try_metadata(path, fmt):
    try:
        return read_metadata(path, fmt), None
    except Exception as exc:  # pyuvdata raises many exception types for corrupt files
        return None, exc


def _unreadable(f, exc, on_bad, skipped):
    msg = f"{f}: unreadable ({type(exc).__name__}: {exc})"
    if on_bad != "skip":
        raise InputError(f, "file", f"pyuvdata cannot read it ({exc})",
                         "remove or replace the file, or set input.on_bad_file=skip") from exc
    log.warning("skipping %s", msg)
    skipped.append(msg)


def _metadata_pyuvdata(files, fmt, on_bad, calibrated_here=False):
    """Every file's metadata with pyuvdata (read concurrently), each checked against the first."""
    with ThreadPoolExecutor(max(1, min(n_threads(), len(files)))) as ex:
        results = list(ex.map(lambda f: _try_metadata(f, fmt), files))
    metas, good, skipped = [], [], []
    for f, (uv, exc) in zip(files, results):
        if exc is None:
            metas.append(uv)
            good.append(f)
        else:
            _unreadable(f, exc, on_bad, skipped)
    if not metas:
        raise InputError(files[0], "input.path", "no readable file", "check the files (see the skipped list)")
    ref = metas[0]
    for f, uv in zip(good[1:], metas[1:]):  # frequencies may differ: subbands, grouped by the plan
        checks.compare_telescope(uv, ref, f, good[0])
    infos = [checks.file_info(uv, f, calibrated_here) for f, uv in zip(good, metas)]
    return metas, good, skipped, infos


def _metadata_indexed(files, fmt, on_bad, kind, calibrated_here=False):
    """Many files of one kind: pyuvdata for the first, a cheap read of the columns the plan needs
    for the rest (``mmflow.io.ms_index`` with python-casacore, ``mmflow.io.uvh5_index`` with h5py),
    each checked against the first. None where that does not apply (then pyuvdata reads them all):
    the first file's phase state is not the one the index handles, or its index disagrees with
    pyuvdata's read of it."""
    indexer = ms_index if kind == "ms" else uvh5_index
    phase = {"ms": "phased", "uvh5": "drift"}[kind]
    skipped, indices, ref_uv = [], [], None
    for f in files:
        try:
            if ref_uv is None:
                ref_uv = read_metadata(f, fmt)
                ref_file = f
            indices.append(indexer.read_index(f, compact=bool(indices)))  # the first whole: checked against pyuvdata
        except InputError:  # a readable file the index refuses (duplicated rows): its own message
            raise
        except Exception as exc:  # corrupt files raise many exception types
            if ref_uv is not None and not indices:
                return None  # the first file reads with pyuvdata but not with the index
            _unreadable(f, exc, on_bad, skipped)
    if ref_uv is None or not indices:
        return None
    indexer.convert_times(indices)
    if indices[0].path != str(ref_file).rstrip("/") or not index_agrees(indices[0], ref_uv):
        log.warning("%s index of %s disagrees with pyuvdata's read: reading every file's metadata with pyuvdata",
                    kind, ref_file)
        return None
    info = checks.file_info(ref_uv, ref_file, calibrated_here)
    if info["phase"] != phase:
        return None
    indexer.check_against(indices[1:], indices[0], ref_uv, info)
    good = [ix.path for ix in indices]
    good[0] = ref_file
    return [ref_uv] + indices[1:], good, skipped, [info] * len(indices)


def index_agrees(ix, uv):
    """True when a cheap index describes pyuvdata's read of the same file (times to 1 us, the
    same (time, baseline) rows in the same order)."""
    return (len(ix.time_array) == uv.Nblts and np.allclose(ix.time_array, uv.time_array, rtol=0, atol=1e-6 / 86400)
            and np.array_equal(ix.ant_1_array, uv.ant_1_array) and np.array_equal(ix.ant_2_array, uv.ant_2_array))


def _file_freqs(meta):
    """A file's channel frequencies (Hz) from its pyuvdata metadata or cheap index."""
    return np.asarray(meta.freq_array if hasattr(meta, "freq_array") else meta.freqs, float).ravel()


def _channel_plan(good, metas, want_mhz, n_avg):
    """``(freqs_hz, width_hz, per-file {"out", "blocks"}, set_of_file)``: the kept channels
    (:mod:`mmflow.io.channels`) and, for every file, which output channels it holds and the blocks of
    its own channels that make them."""
    sets, set_of = frequency_sets([_file_freqs(m) for m in metas])
    width = float(np.median(np.abs(np.asarray(metas[0].channel_width, float)))) \
        if getattr(metas[0], "channel_width", None) is not None else float(np.median(np.diff(sets[0]))) \
        if len(sets[0]) > 1 else 0.0
    outs = select_channels(sets, width, want_mhz, n_avg, good[0] if len(good) == 1 else f"{len(good)} input files",
                           [good[set_of.index(k)] for k in range(len(sets))])
    freqs = np.array([sets[k][b].mean() for k, b in outs])
    per_set = [{"out": [o for o, (k, _) in enumerate(outs) if k == s],
                "blocks": [[int(c) for c in b] for k, b in outs if k == s]} for s in range(len(sets))]
    return freqs, width * n_avg, [per_set[k] for k in set_of], set_of


@lru_cache(maxsize=4)
def plan_ingest(pattern, fmt=None, on_bad="error", calibrated_here=False, want_mhz=None, n_avg=1, cross_hands=True,
                pol_convention="auto"):
    """The ingest plan of the files ``pattern`` matches (every file's metadata and checks; cached: a
    stage's check and its prepare share it). Plain arguments: the workflow passes its ``input`` settings
    (:func:`mmflow.workflow.engine.ingest_plan.ingest_plan`).

    Parameters
    ----------
    pattern : str
        A file, a glob, or a directory of data files (``input.path``).
    fmt : str, optional
        Force a format (``uvh5``, ``uvfits``, ``ms``).
    on_bad : str
        ``"error"`` stops at a file that cannot be used, ``"skip"`` logs and counts it.
    calibrated_here : bool
        Units other than Jy / K sr are accepted only when the run calibrates.
    want_mhz : tuple of float, optional
        The channels to keep (nearest), else every channel.
    n_avg : int
        Channels averaged into one.
    cross_hands : bool
        Keep xy, yx beside the parallel hands.
    pol_convention : str
        ``auto`` (the file's own), ``sum`` or ``avg``.
    """
    files = _files(pattern)
    fast = None
    kinds = {file_kind(f, fmt) for f in files}
    if len(files) > 2 and len(kinds) == 1 and kinds <= {"ms", "uvh5"}:
        fast = _metadata_indexed(files, fmt, on_bad, kinds.pop(), calibrated_here)
    metas, good, skipped, infos = fast or _metadata_pyuvdata(files, fmt, on_bad, calibrated_here)
    ref = metas[0]
    if not cross_hands:  # input.cross_hands=false: the Stokes-I hands only
        infos = [{**info, "cross_indices": [], "cross_numbers": [], "cross_pols": []} for info in infos]
    for f, info in zip(good, infos):
        kept, ref_kept = info["pols"] + info["cross_pols"], infos[0]["pols"] + infos[0]["cross_pols"]
        if kept != ref_kept:
            raise InputError(f, "polarization_array", f"keeps polarisations {kept} where {good[0]} keeps "
                             f"{ref_kept}", "ingest files with the same polarisations in one run")
    # the hands in mmflow's convention (XX = I for an unpolarised source): pyuvdata's "sum" data doubled
    factor, convention = pol_factor(infos[0]["pol_convention"], pol_convention, calibrated_here, good[0])
    infos = [{**info, "pol_factor": factor, "pol_convention_used": convention} for info in infos]
    freqs, width, chans, set_of = _channel_plan(good, metas, want_mhz, n_avg)
    infos = [{**info, **ch} for info, ch in zip(infos, chans)]
    keep = [k for k, ch in enumerate(chans) if ch["out"]]  # files holding no kept channel are not read
    good, metas, infos, set_of = ([x[k] for k in keep] for x in (good, metas, infos, set_of))
    ants = np.asarray(ref.telescope.antenna_numbers)
    # baselines: the union over files as (i, j) antenna-index pairs with i <= j; a baseline a
    # file lacks is simply unmeasured (weight 0) in that file's integrations
    index = _index_lookup(ants)
    found = []
    for f, uv in zip(good, metas):
        a1, a2 = np.asarray(uv.ant_1_array), np.asarray(uv.ant_2_array)
        if max(a1.max(), a2.max()) >= len(index) or min(index[a1].min(), index[a2].min()) < 0:
            raise InputError(f, "ant_1_array/ant_2_array", f"antenna numbers outside {good[0]}'s antenna table",
                             "ingest files from one array configuration per run")
        found.append(np.sort(np.stack([index[a1], index[a2]], 1), 1))
    pairs = np.stack(checks.distinct_pairs(*np.concatenate(found).T), 1)
    # the antennas with data: an antenna table may list many more (the OVRO-LWA's MS lists 256
    # stands for 20 with data); the layout and every per-antenna array keep only these
    used = np.unique(pairs)
    renumber = np.full(len(ants), -1, int)
    renumber[used] = np.arange(len(used))
    pairs, ants = renumber[pairs], ants[used]
    seen, all_t = {}, {}
    for fi, uv in enumerate(metas):  # an integration once per subband (frequency set)
        for t in np.unique(np.asarray(uv.time_array)):
            key = round(float(t) * 86400.0, 3)
            if (key, set_of[fi]) in seen:
                raise InputError(good[fi], "time_array", f"integration at JD {t:.6f} also in "
                                 f"{good[seen[key, set_of[fi]]]}", "remove duplicated files or integrations")
            seen[key, set_of[fi]] = fi
            all_t.setdefault(key, float(t))
    times = np.array(sorted(all_t.values()))
    keys = _time_key(times)
    file_rows = np.array([[np.searchsorted(keys, _time_key(np.min(uv.time_array))),
                           np.searchsorted(keys, _time_key(np.max(uv.time_array)))] for uv in metas], np.int64)
    enu = _antenna_enu(ref)[used]
    lat, lon, alt = ref.telescope.location_lat_lon_alt_degrees
    names = [str(ref.telescope.antenna_names[k]) for k in used]
    layout = Layout(names, enu, float(lat), float(lon), float(alt), provenance=f"ingested from {good[0]}")
    tint = float(np.median(np.asarray(ref.integration_time)))
    return IngestPlan(good, times, file_rows, len(times), freqs, width, pairs, ants, layout,
                      float(np.median(times)), tint, skipped, infos)


def refuse_nonfinite(plan, fmt=None):
    """Refuse unflagged NaN/inf samples before any task (``input.nonfinite=error``), naming every file
    that has them: each planned file's kept samples read directly (concurrently; UVH5 with h5py,
    MeasurementSets with python-casacore: :func:`mmflow.io.readers.unflagged_nonfinite`), as its task
    would check them. Files without a direct read (uvfits) are left to their tasks.

    Raises
    ------
    InputError
        Naming the first file with such samples, their count, the other files and the fix.
    """
    site = (plan.layout.lat_deg, plan.layout.lon_deg, plan.layout.height_m)
    with ThreadPoolExecutor(max(1, min(n_threads(), len(plan.files)))) as ex:
        found = list(ex.map(lambda fi: unflagged_nonfinite(plan.files[fi], fmt, plan.file_info[fi], site),
                            range(len(plan.files))))
    bad = [(f, r) for f, r in zip(plan.files, found) if r is not None and r[0]]
    if bad:
        (first, (n, size)), others = bad[0], [(f, r[0]) for f, r in bad[1:]]
        raise checks.nonfinite_error(first, n, size, others)


def plan_arrays(plan):
    """What ingest's tasks need of the plan, as :func:`mmflow.io.run_stores.vis_store` declares it
    (``ingest_plan``): row times, each file's rows, antenna numbers; with ``plan.file_info`` in the
    store's attribute ``ingest_file_info`` (per-file phase state, units, Stokes-I recipe) no worker
    rescans or re-checks files."""
    return (np.asarray(plan.row_time, "float64"), np.asarray(plan.file_rows, "int64"),
            np.asarray(plan.ant_numbers, "int64"))


def _index_lookup(ant_numbers):
    """Dense array taking an antenna number to its index (-1 where unknown)."""
    ant_numbers = np.asarray(ant_numbers, int)
    lut = np.full(int(ant_numbers.max()) + 1, -1, int)
    lut[ant_numbers] = np.arange(len(ant_numbers))
    return lut


def _antenna_enu(uv):
    from pyuvdata.utils import ENU_from_ECEF  # deferred: pyuvdata takes 2-3.5 s to import (docs/performance.md)

    ecef = np.asarray(uv.telescope.antenna_positions) + np.asarray(uv.telescope._location.xyz())
    return ENU_from_ECEF(ecef, center_loc=uv.telescope.location)


def _time_key(jd):
    return checks.time_key(jd)


def ingest_time_chunk(store_path, row0, row1, *, fmt=None, nonfinite="error", conjugate=False):
    """Read the files holding rows ``row0..row1`` (from the plan in the store) and write those rows.

    Nothing is written if any of the files has unflagged NaN/inf samples (unless
    ``input.nonfinite`` is ``"flag"``: they are then flagged, counted and logged). Flagged
    non-finite samples are stored as 0 with weight 0, so ``vis.zarr`` holds only finite numbers.
    ``fmt``, ``nonfinite``, ``conjugate``: the workflow's ``input.format``, ``input.nonfinite`` and
    ``input.conjugate``.
    """
    g = zarr.open_group(str(store_path), mode="r+")
    files = g.attrs["files"]
    infos = g.attrs.get("ingest_file_info")
    row_time = g[STORES.vis.plan_time_jd][row0:row1]
    file_rows = g[STORES.vis.plan_file_rows][:]
    pairs, ant_numbers = g[STORES.vis.pairs][:], g[STORES.vis.antenna_numbers][:]
    freqs = g[STORES.vis.freqs_hz][:]
    n, nbl, nf, npol = len(row_time), len(pairs), len(freqs), g[STORES.vis.vis].shape[3]
    npar = npol
    cross = STORES.vis.vis_cross
    npol += g[cross].shape[3] if cross in g else 0  # the cross hands follow the Stokes-I hands
    mode = nonfinite
    chunk_keys = _time_key(row_time)
    index = _index_lookup(ant_numbers)
    na = len(ant_numbers)
    pair_lut = np.full((na, na), -1, int)
    pair_lut[pairs[:, 0], pairs[:, 1]] = np.arange(nbl)
    fis = [int(f) for f in np.flatnonzero((file_rows[:, 0] < row0 + len(row_time)) & (file_rows[:, 1] >= row0))]

    site = (g.attrs["lat_deg"], g.attrs["lon_deg"], g.attrs["height_m"]) if "lat_deg" in g.attrs else None

    def one(fi):
        return read_file(files[fi], fmt, None if infos is None else infos[fi], site)

    with ThreadPoolExecutor(max(1, min(n_threads(), len(fis)))) as ex:
        parts = list(ex.map(one, fis))
    vis = np.zeros((n, nbl, nf, npol), np.complex64)
    wts = np.zeros((n, nbl, nf, npol), np.float32)
    lst = np.full(n, np.nan)
    n_nonfinite = 0
    for fi, p in zip(fis, parts):
        bad, nbad = checks.nonfinite(p.vis, p.flags, files[fi], mode)  # raises before anything is written
        n_nonfinite += nbad
        out = np.asarray(infos[fi]["out"], int)
        v, fl, ns = average_channels(p.vis, p.flags | bad, p.nsample, [np.asarray(b) for b in infos[fi]["blocks"]])
        keys = _time_key(p.time_jd)
        pos = np.searchsorted(chunk_keys, keys)
        mine = (pos < n) & (chunk_keys[np.minimum(pos, n - 1)] == keys)  # rows of other chunks are skipped
        r = pos[mine]
        i, j = index[p.ant1[mine]], index[p.ant2[mine]]
        swap = i > j  # V(j, i) = conj(V(i, j))
        b = pair_lut[np.minimum(i, j), np.maximum(i, j)]
        v, fl, ns = v[mine], fl[mine], ns[mine]
        finite = np.isfinite(v)
        if not finite.all():  # flagged (or, with nonfinite=flag, newly flagged) NaN/inf are stored as 0
            v = np.where(finite, v, 0)
        if swap.any():
            v[swap] = np.conj(v[swap])
            if npol - npar == 2:  # V_xy(i, j) = conj(V_yx(j, i)): the cross hands trade places
                perm = list(range(npar)) + [npar + 1, npar]
                for x in (v, fl, ns, finite):
                    x[swap] = x[swap][:, :, perm]
            elif npol > npar:  # the other cross hand is not in the file
                fl[swap, :, npar:] = True
        if conjugate:
            v = np.conj(v)
        vis[r[:, None], b[:, None], out[None, :]] = v
        wts[r[:, None], b[:, None], out[None, :]] = np.where(fl | ~finite, 0.0, ns)
        lst[r] = p.lst[mine]
    g[STORES.vis.vis][row0:row0 + n] = vis[..., :npar]
    g[STORES.vis.weights][row0:row0 + n] = wts[..., :npar]
    if npol > npar:
        g[STORES.vis.vis_cross][row0:row0 + n] = vis[..., npar:]
        g[STORES.vis.weights_cross][row0:row0 + n] = wts[..., npar:]
    g[STORES.vis.lst][row0:row0 + n] = lst
    g[STORES.vis.time_jd][row0:row0 + n] = row_time
    flagged = int(np.sum(np.all(wts[..., :npar] == 0, axis=(1, 2, 3))))
    return {"integrations": int(n), "fully_flagged_integrations": flagged, "files_read": len(fis),
            "nonfinite_flagged": int(n_nonfinite)}


def sidereal_coverage(plan, n_bins):
    """Fraction of ``n_bins`` sidereal bins that hold at least one of the plan's integrations (the
    most any baseline can cover: :func:`mmflow.mmode.transform.bin_coverage` of every row's LST
    at the site, as the m-mode stage bins them)."""
    lst = apparent_sidereal_time(np.asarray(plan.row_time), plan.layout.lon_deg)
    return bin_coverage(lst, n_bins)
