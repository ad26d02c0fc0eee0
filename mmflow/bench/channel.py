"""``mmflow bench channel``: one real channel through transfer, Gram and solve, measured per phase.

The case is a named layout at one frequency and lmax (default: the paper's channel,
``ovro_lwa_layout("paper-2017")``, 256 stands, 32,896 baselines with autos, 73.152 MHz,
lmax 1000, float32). ``--scale F`` runs every ``1/F``-th baseline chunk of the full plan
(chunks are sorted by per-baseline lmax, so the subsample spans every baseline length with
the full run's chunk sizes and cost mix); ``--scale 1`` is the full channel.

For each scale the JSON gives, side by side:

* ``measured``: wall seconds per phase (grid setup, Legendre tables, Fourier, Legendre
  GEMMs, mask/weights, Gram ``herk``, right-hand side, solve), peak RSS;
* ``model``: the same phases projected from work counts (points, flops, table entries of
  the case's own chunk plan) divided by kernel rates measured on synthetic chunks at the
  start of the same run (``calibration``), for the measured subsample (the check: the
  ratio should be within 20 %) and for the full channel (``projection_full_channel``);
* the SGEMM/DGEMM peaks measured in the same run (the VM's BLAS peak swings ~2x).

Per-pool phases (tables, Legendre, masks, herk, rhs) run on ``n_threads()`` threads: their
thread-seconds are converted to wall seconds by their share of the per-m pool's wall time.
The solve runs all m at full lmax at any scale (``--solve-stride N``: every N-th m, the rest
projected by ``n^3``). ``--workflow`` also runs the workflow's transfer/normal/solve stages on
a local cluster of ``--workers`` processes (after simulate/mmodes, which are not counted).
Progress goes to stderr, the JSON to stdout.
"""
from __future__ import annotations

import os
import resource
import sys
import tempfile
import time

import ducc0
import numpy as np

from mmflow.bench.engine import BEAM, LAT, full_lmax_baselines
from mmflow.imaging.solvers import solve_alm
from mmflow.machine import gemm_gflops, machine
from mmflow.mmode.engine import GridCache, accumulate_chunks, plan_chunks
from mmflow.mmode.normal import NormalAccumulator
from mmflow.mmode.transfer import baselines_in_wavelengths, fringe_bandlimit, make_grid, transfer_pass
from mmflow.telescope import Telescope, ovro_lwa_layout
from mmflow.telescope.beams import SinElevationBeam
from mmflow.threads import n_threads
from mmflow.workflow.engine.cluster import open_cluster
from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.rundir import RunDir
from mmflow.workflow.engine.runner import run_workflow
from mmflow.conventions import complex_dtype

POOL_PHASES = ("tables_s", "legendre_s", "scale_s", "herk_s", "rhs_s")
PAPER = {"layout": "paper-2017", "freq_mhz": 73.152, "lmax": 1000}
#: The paper's eight channels (MHz).
PAPER_FREQS_MHZ = tuple(round(36.528 + 5.232 * k, 3) for k in range(8))


def _log(msg):
    print(f"[bench channel {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _vm_hwm_mb():
    """Peak resident memory of this process's own address space (``VmHWM``; ``ru_maxrss``
    survives fork+exec and can report a parent's peak)."""
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith("VmHWM")) / 1024.0


def telescope_for(layout, freq_hz):
    return Telescope(ovro_lwa_layout(layout), SinElevationBeam(1.5), [freq_hz])


def subsample(chunks, scale):
    """Every ``1/scale``-th chunk of the lmax-sorted plan, centred in each stride."""
    if scale >= 1:
        return list(chunks)
    stride = max(1, int(round(1.0 / scale)))
    return list(chunks[stride // 2::stride]) or [chunks[len(chunks) // 2]]


# ---------------------------------------------------------------- work counts (the model's inputs)

def _grid_shape(lg, fringe):
    quad = lg + fringe
    n_theta = quad // 2 + 2
    n_theta += n_theta % 2
    return n_theta // 2, ducc0.fft.good_size(quad + 2)


def _grid_key(chunk_lmax, fringe, cap):
    step, fstep = max(16, cap // 16), max(16, cap // 8)
    return min(cap, int(step * np.ceil(chunk_lmax / step))), int(fstep * np.ceil(fringe / fstep))


def chunk_work(nb, lc, lg, fringe, mmax):
    """Work units of one chunk of ``nb`` baselines with lmax ``lc`` on grid ``(lg, fringe)``."""
    nn, nphi = _grid_shape(lg, fringe)
    mtop = min(mmax, lc)
    n = lc - np.arange(mtop + 1) + 1.0
    rows = np.full(mtop + 1, 2.0 * nb)
    rows[0] = nb
    return {"fourier": float(nn * nphi * np.log2(nphi) * nb),  # fringes + ring FFTs ~ nn nphi log(nphi) nb
            "fourier_points": float(nn * nphi * nb),
            "legendre": float(8.0 * nb * nn * n.sum()),  # untrimmed GEMM flops (tables trim poleward rings)
            "herk": float((4.0 * rows * n * (n + 1)).sum()),
            "elements": float((2.0 * nb * n).sum())}


def grid_work(lg, fringe):
    nn, nphi = _grid_shape(lg, fringe)
    return {"tables": nn * (lg + 1.0) * (lg + 2.0) / 2.0, "grid_points": float(2 * nn * nphi)}


def plan_work(tel, freq_hz, lmax, chunks):
    """Work units summed over ``chunks`` in order, with a grid build wherever the grid key changes."""
    tot = {"fourier": 0.0, "fourier_points": 0.0, "gram_bytes": 0.0, "legendre": 0.0, "herk": 0.0, "elements": 0.0,
           "tables": 0.0, "grid_points": 0.0, "grid_builds": 0, "chunks": len(chunks),
           "baselines": int(sum(len(c.index) for c in chunks))}
    prev = None
    pairs = tel.antenna_pairs()
    # Gram pages written for the first time (upper triangles of the leading blocks the chunks reach)
    top = max(c.lmax for c in chunks)
    n_m = np.maximum(top - np.arange(top + 1) + 1.0, 0)
    tot["gram_bytes"] = float((n_m * (n_m + 1) / 2).sum() * 8)  # complex64 accumulators
    for c in chunks:
        b = baselines_in_wavelengths(tel, pairs[c.index], freq_hz)
        key = _grid_key(c.lmax, fringe_bandlimit(np.linalg.norm(b, axis=1), tel.beam.lmax_hint), lmax)
        if key != prev:
            for k, v in grid_work(*key).items():
                tot[k] += v
            tot["grid_builds"] += 1
            prev = key
        for k, v in chunk_work(len(c.index), c.lmax, key[0], key[1], lmax).items():
            tot[k] += v
    return tot


# ---------------------------------------------------------------- calibration and model

def calibrate(dtype, lmaxes, nb=64):
    """Kernel rates (work units per second) on synthetic chunks whose baselines all need ``L``."""
    out = []
    fresh = np.zeros(1 << 26, np.complex64)  # 512 MB never touched
    t0 = time.perf_counter()
    fresh.view(np.float32)[::1024] = 1.0  # one write per 4 KiB page: page faults and zeroing
    touch_rate = fresh.nbytes / (time.perf_counter() - t0)
    del fresh
    for lmax in lmaxes:
        n = nb
        b = full_lmax_baselines(lmax, n, seed=lmax)
        fringe = fringe_bandlimit(np.linalg.norm(b, axis=1), BEAM.lmax_hint)
        lg, fr = _grid_key(lmax, fringe, lmax)
        t0 = time.perf_counter()
        grid = make_grid(LAT, BEAM, 73.152e6, lg, fr)
        grid_s = time.perf_counter() - t0
        acc = NormalAccumulator(lmax, lmax, complex_dtype(dtype).type)
        vw = np.ones((1, 2 * n), acc.dtype)
        tim = {}

        def consume(m, o, t):
            acc.add_scaled_block(m, o, n if m == 0 else 2 * n, o.shape[0], vw[:, :n if m == 0 else 2 * n], t)

        t0 = time.perf_counter()
        transfer_pass(grid, b, consume, np.full(n, lmax), lmax, dtype, lmax, np.ones(n), tim)
        wall = time.perf_counter() - t0
        # a second pass on the same grid (tables built, Gram pages touched): the best of two per phase,
        # as the shared machine's load comes and goes
        again = {}
        t0 = time.perf_counter()
        transfer_pass(grid, b, consume, np.full(n, lmax), lmax, dtype, lmax, np.ones(n), again)
        wall = min(wall, time.perf_counter() - t0)
        for k, v in again.items():
            if k != "tables_s" and k.endswith("_s"):
                tim[k] = min(tim[k], v)
        w = chunk_work(n, lmax, lg, fr, lmax)
        g = grid_work(lg, fr)
        pool_thread_s = sum(again.get(p, 0.0) for p in POOL_PHASES)
        out.append({"lmax": lmax, "baselines": n, "wall_s": wall, "timings": tim,
                    "rates": {"fourier": w["fourier"] / tim["fourier_s"],
                              "tables": g["tables"] / tim["tables_s"],
                              "legendre": w["legendre"] / tim["legendre_s"],
                              "herk": w["herk"] / tim["herk_s"],
                              "elements": w["elements"] / (tim.get("scale_s", 0.0) + tim["rhs_s"]),
                              "grid_points": g["grid_points"] / grid_s, "gram_bytes": touch_rate},
                    "pool_efficiency": pool_thread_s / (again["mpool_s"] * n_threads()),
                    "legendre_gflops_actual": tim["legendre_flops"] / tim["legendre_s"] / 1e9 * n_threads(),
                    "herk_gflops": tim["herk_flops"] / tim["herk_s"] / 1e9 * n_threads()})
    return out


def model_seconds(work, cal):
    """Wall seconds per phase: work units / calibrated rates.

    Rates are interpolated in log lmax between the calibrations, at the case's cost-weighted
    mean chunk lmax; pool phases are divided by ``n_threads()`` times the pool efficiency
    measured in the calibration.
    """
    rates, eff = _blend(cal, work.get("mean_lmax", cal[-1]["lmax"]))
    thr = n_threads()
    pool = {"tables_s": work["tables"] / rates["tables"], "legendre_s": work["legendre"] / rates["legendre"],
            "herk_s": work["herk"] / rates["herk"], "rhs_scale_s": work["elements"] / rates["elements"]}
    pool_wall = {k: v / (thr * eff) for k, v in pool.items()}
    res = {"grid_s": work["grid_points"] / rates["grid_points"], "fourier_s": work["fourier"] / rates["fourier"],
           "gram_first_touch_s": work["gram_bytes"] / rates["gram_bytes"]}
    res.update(pool_wall)
    res["transfer_and_gram_s"] = sum(res.values())
    return res


def _blend(cal, lmax):
    ls = np.log([c["lmax"] for c in cal])
    x = np.clip(np.log(max(lmax, 1)), ls.min(), ls.max())
    wts = np.interp(x, ls, np.arange(len(ls)))
    i0 = int(np.floor(wts))
    i1 = min(i0 + 1, len(cal) - 1)
    f = wts - i0
    rates = {k: float(np.exp((1 - f) * np.log(cal[i0]["rates"][k]) + f * np.log(cal[i1]["rates"][k])))
             for k in cal[0]["rates"]}
    eff = (1 - f) * cal[i0]["pool_efficiency"] + f * cal[i1]["pool_efficiency"]
    return rates, min(1.0, eff)


def _mean_lmax(tel, freq_hz, lmax, chunks):
    """Cost-weighted mean chunk lmax (~ n lmax^3 weights): where the case's time is spent."""
    lc = np.array([c.lmax for c in chunks], float)
    wt = np.array([len(c.index) for c in chunks], float) * lc ** 3
    return float(np.exp((wt * np.log(np.maximum(lc, 1))).sum() / wt.sum()))


# ---------------------------------------------------------------- the measured run

def measure_engine(tel, freq_hz, lmax, chunks, lmax_b, dtype, solve_stride=1, eps=0.01):
    acc_dtype = complex_dtype(dtype).type
    acc = NormalAccumulator(lmax, lmax, acc_dtype)
    n_bl = len(lmax_b)
    inv_var = np.ones(n_bl)

    def mmodes_of(chunk):  # random data, so the right-hand side is real work
        rng = np.random.default_rng(int(chunk.index[0]))
        shape = (1, lmax + 1, 2, len(chunk.index))
        return (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(acc_dtype)

    t_start = time.perf_counter()

    def progress(i, n, chunk):
        el = time.perf_counter() - t_start
        _log(f"chunk {i + 1}/{n} (lmax {chunk.lmax}, {len(chunk.index)} baselines) {el:.1f} s, "
             f"rss {_rss_mb():.0f} MB")

    tim = {}
    cache = GridCache(tel, freq_hz)
    t0 = time.perf_counter()
    accumulate_chunks(acc, tel, freq_hz, chunks, lmax_b, mmodes_of, inv_var, dtype, cache, timings=tim,
                      progress=progress)
    wall = time.perf_counter() - t0
    tim["grid_s"] = cache.build_s
    pool_thread = sum(tim.get(p, 0.0) for p in POOL_PHASES)
    share = tim.get("mpool_s", 0.0) / pool_thread if pool_thread else 0.0
    phases = {"grid_s": tim["grid_s"], "fourier_s": tim.get("fourier_s", 0.0)}
    for p in POOL_PHASES:
        phases[p] = tim.get(p, 0.0) * share
    phases["rhs_scale_s"] = phases.pop("rhs_s") + phases.pop("scale_s")
    phases["other_s"] = wall - sum(phases.values())
    res = {"wall_s": wall, "phases_s": phases, "thread_seconds": tim, "grid_builds": cache.builds,
           "legendre_gflops": tim.get("legendre_flops", 0.0) / max(tim.get("legendre_s", 1e-9), 1e-9) / 1e9
           * n_threads(),
           "herk_gflops": tim.get("herk_flops", 0.0) / max(tim.get("herk_s", 1e-9), 1e-9) / 1e9 * n_threads(),
           "peak_rss_mb": _rss_mb()}
    _log(f"transfer + Gram {wall:.1f} s; solving {lmax + 1} m blocks (stride {solve_stride})")
    res["solve"] = measure_solve(acc, lmax, eps, solve_stride)
    res["peak_rss_mb"] = _rss_mb()
    return res


def measure_solve(acc, lmax, eps, stride=1):
    """Tikhonov solve + fraction of singular values above sqrt(eps) for every ``stride``-th m."""
    ms = list(range(0, lmax + 1, stride))
    sizes = np.array([lmax - m + 1.0 for m in ms])
    t0 = time.perf_counter()
    solve_alm(acc, eps, ms=ms)
    el = time.perf_counter() - t0
    all_cubes = ((lmax - np.arange(lmax + 1) + 1.0) ** 3).sum()
    return {"m_solved": len(ms), "seconds": el, "projected_all_m_s": el * all_cubes / (sizes ** 3).sum()}


def measure_workflow(layout, freq_mhz, lmax, scale, workers, dtype, root):
    """The workflow's transfer/normal/solve stages on a local cluster (simulate/mmodes not counted).

    The workflow has no baseline-subsample setting: ``scale < 1`` keeps the first
    ``256 sqrt(scale)`` stands instead (a different baseline mix than the engine's subsample).
    ``transfer.groups`` is the number of workers: every group writes a full-lmax partial Gram
    (2.7 GB at lmax 1000 in float32) that the ``normal`` stage reads back.
    """
    over = [f"telescope.preset={layout}", "telescope.radius_m=null", f"observation.freqs_mhz=[{freq_mhz}]",
            "sky.diffuse=false", "sky.sources=[Cyg A, Cas A]", "sky.noise=false", f"mmode.lmax={lmax}",
            f"transfer.dtype={np.dtype(dtype).name}", "transfer.noise_weighting=false", "transfer.baseline_chunk=64",
            f"transfer.groups={workers}", "imaging.lcurve=false", "products.nside=64",
            "cluster.kind=local", f"cluster.n_workers={workers}", "cluster.threads_per_worker=1",
            "cluster.dashboard_address=:0", f"run.directory={root}/wf"]
    if scale < 1:
        over.append(f"telescope.max_antennas={workflow_antennas(scale)}")
    demo = os.path.join(os.path.dirname(__file__), "..", "..", "workflows", "demo.yaml")
    cfg = load_config(demo, over)
    _log("workflow: simulate + mmodes (not counted)")
    run_workflow(cfg, None, only=["simulate", "mmodes"], progress=False, log=lambda *a: None)
    out = {"overrides": over, "workers": workers}
    with open_cluster(cfg, None, None, log=lambda *a: None) as client:
        t0 = time.perf_counter()
        summaries = run_workflow(cfg, client, only=["transfer", "normal", "solve"], progress=False,
                                 log=lambda msg: _log(f"workflow: {msg}"))
        out["wall_s"] = time.perf_counter() - t0
        out["stages_s"] = {k: v["wall_s"] for k, v in summaries.items()}
        out["stages"] = {k: {q: v.get(q) for q in ("wall_s", "task_s", "checksum_s", "guard_s", "bytes_written")}
                         for k, v in summaries.items()}
        rss = client.run(_vm_hwm_mb)

        out["transfer_tasks"] = RunDir(cfg.run.directory).task_infos("transfer")
        out["peak_rss_mb_per_worker"] = sorted(rss.values())
    return out


def workflow_antennas(scale):
    """Stands the workflow keeps at ``scale`` (it has no baseline-subsample setting): ``256 sqrt(scale)``."""
    return None if scale >= 1 else max(2, int(round(256 * np.sqrt(scale))))


def engine_on_workflow_case(layout, freq_mhz, lmax, scale, dtype):
    """The engine on exactly the workflow's case (its first stands), every chunk and every m."""
    f = freq_mhz * 1e6
    tel = Telescope(ovro_lwa_layout(layout, max_antennas=workflow_antennas(scale)), SinElevationBeam(1.5), [f])
    chunks, lmax_b = plan_chunks(tel, f, lmax, 64, True)
    _log(f"engine on the workflow's case: {len(lmax_b)} baselines, {len(chunks)} chunks")
    meas = measure_engine(tel, f, lmax, chunks, lmax_b, dtype, 1)
    return {"baselines": int(len(lmax_b)), "wall_s": meas["wall_s"], "solve_s": meas["solve"]["seconds"],
            "total_s": meas["wall_s"] + meas["solve"]["seconds"], "phases_s": meas["phases_s"]}


def run_case(layout, freq_mhz, lmax, scale, dtype, cal, solve_stride, do_engine=True):
    f = freq_mhz * 1e6
    tel = telescope_for(layout, f)
    chunks, lmax_b = plan_chunks(tel, f, lmax, 64, True)
    sel = subsample(chunks, scale)
    full_w = plan_work(tel, f, lmax, chunks)
    full_w["mean_lmax"] = _mean_lmax(tel, f, lmax, chunks)
    sub_w = plan_work(tel, f, lmax, sel)
    sub_w["mean_lmax"] = _mean_lmax(tel, f, lmax, sel)
    res = {"layout": layout, "freq_mhz": freq_mhz, "lmax": lmax, "dtype": np.dtype(dtype).name, "scale": scale,
           "baselines_total": int(len(lmax_b)), "chunks_total": len(chunks), "chunks_run": len(sel),
           "baselines_run": sub_w["baselines"], "median_baseline_lmax": float(np.median(lmax_b)),
           "grid_builds_full_channel": full_w["grid_builds"]}
    model_sub = model_seconds(sub_w, cal)
    model_full = model_seconds(full_w, cal)
    res["model_for_run"] = model_sub
    if do_engine:
        _log(f"engine: {len(sel)} of {len(chunks)} chunks ({sub_w['baselines']} baselines), lmax {lmax}")
        meas = measure_engine(tel, f, lmax, sel, lmax_b, dtype, solve_stride)
        res["measured"] = meas
        res["model_over_measured"] = model_sub["transfer_and_gram_s"] / meas["wall_s"]
        # the measured run extrapolated by the model's full/subsample ratio (grids counted at full scale)
        extrap = meas["wall_s"] * model_full["transfer_and_gram_s"] / model_sub["transfer_and_gram_s"]
        solve_s = meas["solve"]["projected_all_m_s"]
        res["projection_full_channel"] = {
            "label": "PROJECTION (not measured) unless scale == 1",
            "model_transfer_and_gram_s": model_full["transfer_and_gram_s"], "model_phases_s": model_full,
            "measured_times_model_ratio_transfer_and_gram_s": extrap, "solve_s": solve_s,
            "total_minutes": (extrap + solve_s) / 60.0,
            "table_and_grid_fraction": (model_full["tables_s"] + model_full["grid_s"]) /
            (model_full["transfer_and_gram_s"] + solve_s)}
        res["projection_paper_channels"] = project_channels(layout, lmax, cal, meas["wall_s"] / model_sub[
            "transfer_and_gram_s"], solve_s)
    return res


def project_channels(layout, lmax, cal, measured_over_model, solve_s, freqs_mhz=PAPER_FREQS_MHZ):
    """PROJECTION of each of the paper's channels: the model's transfer + Gram for that channel times
    the measured/model ratio of this run, plus this run's solve (which depends on lmax only)."""
    out = {}
    for fm in freqs_mhz:
        tel = telescope_for(layout, fm * 1e6)
        chunks, _ = plan_chunks(tel, fm * 1e6, lmax, 64, True)
        w = plan_work(tel, fm * 1e6, lmax, chunks)
        w["mean_lmax"] = _mean_lmax(tel, fm * 1e6, lmax, chunks)
        tg = model_seconds(w, cal)["transfer_and_gram_s"] * measured_over_model
        out[f"{fm:.3f}"] = {"transfer_and_gram_s": tg, "solve_s": solve_s, "total_s": tg + solve_s}
    out["all_channels_minutes"] = sum(v["total_s"] for v in out.values()) / 60.0
    out["label"] = "PROJECTION from this run's measured/model ratio"
    return out


def run(what="channel", quick=False, layout=PAPER["layout"], freq_mhz=PAPER["freq_mhz"], lmax=None,
        scales=None, dtype="float32", workflow=False, engine=True, workers=1, solve_stride=1):
    """Measure the channel at each of ``scales`` (fractions of its baseline chunks)."""
    lmax = lmax or (128 if quick else PAPER["lmax"])
    scales = scales or ([0.05] if quick else [0.02, 0.05])
    dt = np.float32 if dtype == "float32" else np.float64
    res = {"machine": machine(), "threads": n_threads(), "cases": []}
    cal_l = sorted({max(64, lmax // 4), max(96, 3 * lmax // 4)})
    calibrate(dt, [32])  # compile the numba kernels (tables, fringes) before anything is timed
    for s in scales:
        # the VM's load comes and goes: peaks and kernel rates are measured next to each case
        _log(f"scale {s}: measuring SGEMM/DGEMM peaks, calibrating kernel rates at lmax {cal_l}")
        peaks = {"sgemm_gflops_before": gemm_gflops(np.float32), "dgemm_gflops_before": gemm_gflops(np.float64)}
        cal = calibrate(dt, cal_l)
        case = run_case(layout, freq_mhz, lmax, s, dt, cal, solve_stride, engine)
        peaks["sgemm_gflops_after"] = gemm_gflops(np.float32)
        peaks["dgemm_gflops_after"] = gemm_gflops(np.float64)
        case["peaks"], case["calibration"] = peaks, cal
        peak = max(peaks["sgemm_gflops_before"], peaks["sgemm_gflops_after"]) if dt == np.float32 else max(
            peaks["dgemm_gflops_before"], peaks["dgemm_gflops_after"])
        if engine:
            case["legendre_fraction_of_gemm_peak"] = case["measured"]["legendre_gflops"] / peak
            case["herk_fraction_of_gemm_peak"] = case["measured"]["herk_gflops"] / peak
        if workflow:
            with tempfile.TemporaryDirectory(prefix="mmflow-bench-channel-") as root:
                case["workflow"] = wf = measure_workflow(layout, freq_mhz, lmax, s, workers, dt, root)
            if s < 1:  # a different case than the engine's subsample: time the engine on it too
                wf["engine_same_case"] = engine_on_workflow_case(layout, freq_mhz, lmax, s, dt)
                eng_total = wf["engine_same_case"]["total_s"]
            else:
                eng_total = case["measured"]["wall_s"] + case["measured"]["solve"]["seconds"] if engine else None
            if eng_total:
                wf["workflow_over_engine"] = wf["wall_s"] / eng_total
        res["cases"].append(case)
    res["peak_rss_mb_this_process"] = _rss_mb()
    return res
