"""Benchmark: ingest of one file per integration against pyuvdata's own read rate, same files, same run.

``run()`` (``mmflow bench ingest``) writes ``n`` single-integration UVH5 files and ``n``
single-integration MeasurementSets (phased to the zenith of their integration, as the OVRO-LWA
writes them; needs python-casacore) of a random drift scan, plus one UVH5 holding all ``n``
integrations, and reports for each set:

* ``raw``: a serial loop of ``pyuvdata.UVData.read`` over the files (default arguments; the best of
  two passes, the files already in the page cache), files/s and MB/s;
* ``ingest``: mmflow's plan (metadata of every file, checks) plus the ingest tasks writing
  ``vis.zarr`` (run one after another in this process, as ``cluster.kind=synchronous`` runs them;
  the faster of two passes, as for pyuvdata), files/s and MB/s, and ``ratio_to_raw`` = ingest
  rate / raw rate = ``raw_read_s / ingest_s``;
* the split between plan and tasks.

``run(raw=True)`` (``mmflow bench ingest --raw``) writes the files as the OVRO-LWA's correlator
does instead (:func:`_scan` with ``raw=True``): one MeasurementSet per 13 s integration, 109
channels of 24 kHz from 27.384 MHz, xx yy xy yx, ``vis_units`` ``uncalib``, each phased to its own
zenith in FK5 J2000 (:func:`mmflow.io.export.write_per_integration`), on the first ``n_ant``
stands of the OVRO-LWA core (real positions), random visibilities. Two cases, each beside
pyuvdata reading the same files in the same run:

* ``select_1``: ingest keeping the file channel nearest 28.680 MHz (``observation.freqs_mhz``);
* ``average_4``: ingest averaging the 4 channels around it (``input.average_channels=4``);

and for each, beside ``raw`` (pyuvdata reading every channel), ``raw_select``: pyuvdata's read of
only the channels ingest keeps (``UVData.read(freq_chans=...)``, then ``frequency_average(4)`` for
the average), with ``ratio_to_raw_select = raw_select_read_s / ingest_s``.

Every measured part reports its wall time (``*_s``) and the process's CPU time (``*_cpu_s``, all
threads): on a shared machine a wall time well above the CPU time of a serial part is time the
process waited for a core. MB are the files' sizes on disk. ``quick=True`` is small enough for a
test; ``keep=True`` leaves the files and each case's run directory (``<case>.run/vis.zarr``) in
``directory``. ``MMFLOW_BENCH_DIR=/dev/shm`` for MS: casacore syncs every table it writes.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from astropy import units as u
from astropy.coordinates import EarthLocation
from pyuvdata import Telescope, UVData
from pyuvdata.utils import ECEF_from_ENU

from mmflow.io import ingest
from mmflow.io.export import write_per_integration
from mmflow.workflow.engine.ingest_plan import ingest_plan, ingest_rows
from mmflow.io.run_stores import vis_store
from mmflow.offline import offline_site_registry
from mmflow.telescope.layout import ovro_lwa_layout
from mmflow.threads import n_threads
from mmflow.workflow.engine.chunking import TIME_CHUNK
from mmflow.workflow.engine.data_stage import layout_attrs

#: the OVRO-LWA's MeasurementSets (the real file in tests/data): 109 channels of 24 kHz from 27.384 MHz
OVRO_F0_HZ, OVRO_DF_HZ, OVRO_N_CHAN = 27.384e6, 24e3, 109
RAW_CHANNEL = 54  # the channel the raw cases keep (28.680 MHz), and average around
RAW_CASES = (("select_1", 1), ("average_4", 4))  # (name, input.average_channels)


def _scan(n_ant, n_freq, n_time, seed=0, raw=False):
    """A random drift scan of 13 s integrations, all baselines with autos, ``V = N(0,1) + i N(0,1)``
    (float32 values; the autocorrelations' parallel hands made real).

    Default: two linear polarisations in Jy (``pol_convention`` avg) on a random 100 m layout at the
    OVRO-LWA site, channels of 24 kHz from 40 MHz. ``raw``: as the OVRO-LWA's correlator writes it:
    the first ``n_ant`` stands of :func:`mmflow.telescope.layout.ovro_lwa_layout` ``("core")``,
    telescope ``OVRO_MMA``, channels of 24 kHz from 27.384 MHz, xx yy xy yx, ``uncalib``, no
    polarisation convention (pyuvdata's for uncalibrated data).
    """
    rng = np.random.default_rng(seed)
    if raw:
        lay = ovro_lwa_layout("core", max_antennas=n_ant)
        (lat, lon, height), enu, names = (lay.lat_deg, lay.lon_deg, lay.height_m), lay.enu, list(lay.names)
        name, f0, pols, units = "OVRO_MMA", OVRO_F0_HZ, [-5, -6, -7, -8], "uncalib"
    else:
        (lat, lon, height), names = (37.2398, -118.2817, 1183.0), [f"A{k}" for k in range(n_ant)]
        enu = np.column_stack([rng.uniform(-50, 50, n_ant), rng.uniform(-50, 50, n_ant), np.zeros(n_ant)])
        name, f0, pols, units = "bench", 40e6, [-5, -6], "Jy"
    loc = EarthLocation.from_geodetic(lon * u.deg, lat * u.deg, height * u.m)
    ecef = ECEF_from_ENU(enu, center_loc=loc) - np.array([loc.x.to_value("m"), loc.y.to_value("m"),
                                                            loc.z.to_value("m")])
    tel = Telescope.new(name, loc, antenna_positions=ecef, antenna_names=names,
                        antenna_numbers=list(range(n_ant)), instrument=name, mount_type="fixed")
    antpairs = [(i, j) for i in range(n_ant) for j in range(i, n_ant)]
    dt = 13.0
    times = 2460000.5 + np.arange(n_time) * dt / 86400.0
    shape = (n_time * len(antpairs), n_freq, len(pols))
    data = (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(np.complex64)
    freqs = f0 + OVRO_DF_HZ * np.arange(n_freq)
    uv = UVData.new(freq_array=freqs, polarization_array=np.array(pols), times=times, telescope=tel,
                    antpairs=antpairs, do_blt_outer=True, data_array=data.astype(np.complex128),
                    integration_time=dt, channel_width=OVRO_DF_HZ, vis_units=units, time_axis_faster_than_bls=False)
    uv._fix_autos()
    if not raw:
        uv.pol_convention = "avg"  # XX = I, as CASA writes (docs/conventions.md)
    return uv


def _write(uv, directory, fmt, phase_frame="icrs"):
    directory.mkdir(parents=True)
    with warnings.catch_warnings():  # pyuvdata warns on every MS that CASA may ignore vis_units
        warnings.simplefilter("ignore")
        return write_per_integration(uv, directory, fmt, phase_frame=phase_frame)


def _size_mb(paths):
    total = 0
    for p in paths:
        p = Path(p)
        total += sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) if p.is_dir() else p.stat().st_size
    return total / 1e6


def _timed(fn):
    """``(wall s, CPU s of this process)`` of ``fn()``."""
    w, c = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w, time.process_time() - c


def _raw_read(paths, freq_chans=None, n_avg=1):
    """pyuvdata's own read of every file, one after another: ``(wall, CPU)`` of the faster of two
    passes. ``freq_chans``: ``UVData.read(freq_chans=...)``, then ``frequency_average(n_avg)``."""
    def one_pass():
        for p in paths:
            uv = UVData()
            uv.read(str(p), freq_chans=freq_chans)
            if n_avg > 1:
                uv.frequency_average(n_avg)

    with warnings.catch_warnings():  # the MS reader warns on every file that it selects after reading
        warnings.simplefilter("ignore")
        return min((_timed(one_pass) for _ in range(2)), key=lambda t: t[0])


def _cfg(pattern, freqs_mhz=None, n_avg=1, calibrate=False):
    """The configuration sections the ingest plan and tasks read, the schema's own with its defaults
    (``calibrate``: accept ``uncalib``)."""
    from mmflow.workflow.config.schema import ObservationConfig  # deferred: as the workflow
    from mmflow.workflow.stages.ingest.settings import InputConfig  # deferred: as the schema
    from mmflow.workflow.stages.calibrate.settings import CalibrateConfig

    return SimpleNamespace(input=InputConfig(path=pattern, average_channels=n_avg),
                           observation=ObservationConfig(freqs_mhz=freqs_mhz),
                           calibrate=CalibrateConfig(enabled=calibrate))


def _ingest(cfg, run_dir, keep=False):
    """mmflow's ingest as the stage runs it: plan and store, then the tasks over time chunks.
    Returns ``((wall, CPU) of the plan, (wall, CPU) of the tasks)``; ``run_dir`` is removed unless ``keep``."""
    ingest.plan_ingest.cache_clear()
    n_threads()  # its first call imports distributed (docs/performance.md): a worker has it loaded already
    found = {}

    def prepare():
        plan = found["plan"] = ingest_plan(cfg)
        spec = vis_store(plan.n_time, plan.pairs, plan.freqs_hz, plan.layout.enu,
                         {**layout_attrs(plan.layout), "source": "ingest", "epoch_jd": plan.epoch_jd,
                          "files": plan.files, "skipped_files": plan.skipped, "integration_s": plan.integration_s,
                          "pols": plan.pols, "cross_pols": plan.cross_pols, "ingest_file_info": plan.file_info},
                         TIME_CHUNK, 256, ingest.plan_arrays(plan))
        spec.create(run_dir)  # the stage's own store declaration
        found["store"] = run_dir / spec.path

    def tasks():
        for r0 in range(0, found["plan"].n_time, TIME_CHUNK):
            ingest_rows(cfg, found["store"], r0, r0 + TIME_CHUNK)

    plan_t, tasks_t = _timed(prepare), _timed(tasks)
    if not keep:
        shutil.rmtree(run_dir)
    return plan_t, tasks_t


def _rates(name, t, n, mb, time_key=None):
    key = time_key or f"{name}_s"
    return {key: round(t[0], 3), f"{key[:-2]}_cpu_s": round(t[1], 3), f"{name}_files_per_s": round(n / t[0], 1),
            f"{name}_mb_per_s": round(mb / t[0], 1)}


def _measure(paths, cfg, run_dir, select=False, keep=False):
    """Rates of pyuvdata's read and of ingest of ``paths``; ``select``: also pyuvdata's read of only the
    channels ``cfg`` keeps (and their average when ``input.average_channels`` > 1)."""
    mb, n = _size_mb(paths), len(paths)
    raw = _raw_read(paths)
    out = {"files": n, "mb": round(mb, 2), **_rates("raw", raw, n, mb, "raw_read_s")}
    if select:
        chans = [int(c) for c in ingest_plan(cfg).file_info[0]["blocks"][0]]
        sel = _raw_read(paths, chans, len(chans))
        out.update(file_channels=chans, **_rates("raw_select", sel, n, mb, "raw_select_read_s"))
    passes = [_ingest(cfg, run_dir, keep and k == 1) for k in range(2)]
    plan_t, tasks_t = min(passes, key=lambda p: p[0][0] + p[1][0])
    ing = (plan_t[0] + tasks_t[0], plan_t[1] + tasks_t[1])
    out.update(**_rates("ingest", ing, n, mb), ingest_plan_s=round(plan_t[0], 3),
               ingest_plan_cpu_s=round(plan_t[1], 3), ingest_tasks_s=round(tasks_t[0], 3),
               ingest_tasks_cpu_s=round(tasks_t[1], 3), ratio_to_raw=round(raw[0] / ing[0], 3))
    if select:
        out["ratio_to_raw_select"] = round(sel[0] / ing[0], 3)
    return out


def _format_cases(root, quick, keep):
    """UVH5 and MS per integration, and one UVH5, of a random 2-polarisation drift scan."""
    n_ant, n_freq, n_time = (16, 8, 24) if quick else (64, 32, 256)
    uv = _scan(n_ant, n_freq, n_time)
    out = {"n_ant": n_ant, "n_baselines": int(uv.Nbls), "n_freq": n_freq, "n_pol": 2, "integrations": n_time}
    paths = _write(uv, root / "uvh5", "uvh5")
    out["uvh5_per_integration"] = _measure(paths, _cfg(str(root / "uvh5" / "*.uvh5")), root / "s1.run", keep=keep)
    one = root / "one" / "all.uvh5"
    one.parent.mkdir()
    uv.write_uvh5(str(one))
    out["uvh5_one_file"] = _measure([one], _cfg(str(one)), root / "s2.run", keep=keep)
    out["per_integration_over_one_file_ingest_time"] = round(
        out["uvh5_per_integration"]["ingest_s"] / out["uvh5_one_file"]["ingest_s"], 2)
    try:
        import casacore  # noqa: F401  # deferred: optional (python-casacore), probed here
    except ImportError:
        out["ms_per_integration"] = "skipped: python-casacore not installed"
    else:
        paths = _write(uv, root / "ms", "ms")
        out["ms_per_integration"] = _measure(paths, _cfg(str(root / "ms" / "*.ms")), root / "s3.run", keep=keep)
    return out


def _raw_cases(root, quick, keep):
    """Raw OVRO-LWA MeasurementSets: one channel kept, and four averaged, beside pyuvdata's reads."""
    try:
        import casacore  # noqa: F401  # deferred: optional (python-casacore), probed here
    except ImportError:
        return {"raw_ms": "skipped: python-casacore not installed"}
    n_ant, n_time = (6, 3) if quick else (64, 30)
    uv = _scan(n_ant, OVRO_N_CHAN, n_time, raw=True)
    out = {"n_ant": n_ant, "n_baselines": int(uv.Nbls), "n_freq": OVRO_N_CHAN, "n_pol": 4, "integrations": n_time,
           "layout": f"OVRO-LWA core, first {n_ant} stands", "vis_units": uv.vis_units, "phase_frame": "fk5"}
    f_mhz = float(uv.freq_array.ravel()[RAW_CHANNEL]) / 1e6
    write = _timed(lambda: out.update(paths=_write(uv, root / "ms", "ms", phase_frame="fk5")))  # noqa: F821 (called before `del uv` below)
    paths = out.pop("paths")
    del uv
    out.update(channel_mhz=round(f_mhz, 6), write_s=round(write[0], 3), write_cpu_s=round(write[1], 3))
    for name, n_avg in RAW_CASES:
        cfg = _cfg(str(root / "ms" / "*.ms"), [f_mhz], n_avg, calibrate=True)
        out[name] = _measure(paths, cfg, root / f"{name}.run", select=True, keep=keep)
    return out


def run(what="ingest", quick=False, directory=None, raw=False, keep=False):
    """Measure; returns a dict (see the module docstring). ``directory``: where to write the files
    (default: the system temporary directory; ``MMFLOW_BENCH_DIR`` overrides); ``raw``: the raw
    OVRO-LWA cases; ``keep``: leave the files and run directories there."""
    offline_site_registry()  # pyuvdata looks OVRO_MMA up among astropy's sites: no download
    root = Path(tempfile.mkdtemp(prefix="mmflow-bench-ingest-",
                                 dir=directory or os.environ.get("MMFLOW_BENCH_DIR")))
    try:
        out = (_raw_cases if raw else _format_cases)(root, quick, keep)
    finally:
        if not keep:
            shutil.rmtree(root, ignore_errors=True)
    return {**out, "threads": n_threads(), "directory": str(root)}


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv, raw="--raw" in sys.argv), indent=2))
