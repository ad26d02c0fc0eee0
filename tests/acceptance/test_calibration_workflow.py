"""End to end: a corrupted drift scan through calibrate -> peel -> terrestrial -> image.

The simulation carries per-antenna, per-polarisation gains (bandpass, slow drift, the HVAC
sawtooth), direction-dependent gains on Cyg A and Cas A (ionospheric refraction and
scintillation), Vir A, Tau A and seven fainter 3C sources, a constant cross-talk pattern and
thermal noise in XX and YY. The chain (the calibration demo, ``workflows/demo-calibrate.yaml``)
calibrates against all eleven sources, peels Cyg A and Cas A, subtracts Vir A and Tau A, fits
the seven fainter ones with them but keeps them (``peel.model_sources``) and removes the
cross-talk, with the calibration settings at their defaults but the sky models, one cross-talk
template and 10-min gain solutions (Cyg A and Cas A screened in the gain solve, the screen peel,
the automatic baseline cuts). Measured on this 26-antenna array (325 baselines; docs/calibration.md): the
map's difference from the clean faint sky is 2.61 K rms against 1235 K uncalibrated, 1.38 x the
thermal-noise map rms (1.90 K; the issue's target 1.5 x); the four removed sources are left at
-44.1, -41.3, -32.4 and -31.8 dB. It was 13.3 K (7.0 x) before the fainter sources were modelled,
the gains interpolated and each integration's DD gains started from 1. The test prints every
figure.
"""
import healpy
import numpy as np
import pytest
import zarr

from mmflow.workflow.config.schema import load_config
from mmflow.workflow.engine.runner import run_workflow
from tests.workflow_helpers import fork_run

QUIET = dict(progress=False, log=lambda *a: None)
BRIGHT = ["Cyg A", "Cas A", "Vir A", "Tau A"]
FAINT = ["3C 123", "3C 48", "3C 147", "3C 196", "3C 286", "3C 295", "3C 380"]
DEMO = "workflows/demo-calibrate.yaml"  # the calibration demo of `make demo`, run here as it is
BASE = ["products.nside=64", "products.png=false", "imaging.lcurve=false", "cluster.kind=synchronous",
        "run.keep=[vis.zarr]"]  # the tests below rerun the calibration chain on these visibilities
OFF = ["calibrate.enabled=false", "peel.enabled=false", "terrestrial.enabled=false"]


def _map(run_dir):
    return healpy.read_map(str(next((run_dir / "maps").glob("map_*.fits"))))


def _run(path, *extra):
    run_workflow(load_config(DEMO, BASE + [f"run.directory={path}", *extra]), **QUIET)
    return _map(path)


# XX and YY with the chain's receiver power but no corruption: the same radiometer weights, so
# the maps differ only by what the chain leaves (Tikhonov maps depend on the noise weighting)
PLAIN = OFF + ["corrupt.gains=false", "corrupt.sawtooth_db=0", "corrupt.dd_sources=[]", "corrupt.crosstalk_jy=0"]


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    d = tmp_path_factory.mktemp("chain")
    out = {
        "chain": _run(d / "chain"),
        # the same sky without corruptions and without the removed sources, noiseless
        "truth": _run(d / "truth", f"sky.sources={FAINT}", "sky.noise=false", *PLAIN),
        # ... and with the chain's thermal noise
        "noisy": _run(d / "noisy", f"sky.sources={FAINT}", *PLAIN),
        # the bright sources alone, to measure their peaks through the same imaging
        "bright": _run(d / "bright", f"sky.sources={BRIGHT}", "sky.noise=false", *PLAIN),
        # the corrupted data imaged as they are (the "before" of the demo): the chain's simulated data
        "raw": _run(fork_run(d / "chain", d / "raw", "simulate"), *OFF),
    }
    out["dir"] = d
    return out


def test_corrupted_chain_brings_the_map_close_to_the_clean_sky(maps):
    seen = maps["truth"] != healpy.UNSEEN
    noise_rms = np.std((maps["noisy"] - maps["truth"])[seen])
    diff_rms = np.std((maps["chain"] - maps["truth"])[seen])
    raw_rms = np.std((maps["raw"] - maps["truth"])[seen])
    truth_rms = np.std(maps["truth"][seen])
    print(f"map difference rms: chain {diff_rms:.4g} K, uncalibrated {raw_rms:.4g} K; clean faint sky "
          f"{truth_rms:.4g} K; thermal-noise map rms {noise_rms:.4g} K (chain / noise = {diff_rms / noise_rms:.1f})")
    assert noise_rms > 0
    assert diff_rms < raw_rms / 300  # measured 2.61 K against 1235 K
    assert diff_rms < 1.5 * noise_rms  # measured 1.38 x (the target: 1.5 x)


def test_peeled_sources_are_suppressed_by_more_than_30_db(maps):
    from mmflow.sky.frames import rotation_matrix
    from mmflow.sky.sources import get_sources
    from mmflow.conventions import radec_to_vec

    nside = healpy.npix2nside(len(maps["truth"]))
    resid = maps["chain"] - maps["truth"]
    rot = rotation_matrix("icrs", "galactic", 2457802.0)
    for src in get_sources(BRIGHT):
        v = rot @ radec_to_vec(np.deg2rad(src.ra_deg), np.deg2rad(src.dec_deg))
        pix = healpy.query_disc(nside, v, np.deg2rad(3.0))
        peak = maps["bright"][pix].max()
        left = np.abs(resid[pix]).max()
        db = 10 * np.log10(left / peak)
        print(f"{src.name}: peak {peak:.4g} K, left {left:.4g} K, {db:.1f} dB")
        if src.name in ("Cyg A", "Cas A"):  # peeled: measured -43.2 and -42.7 dB
            assert db < -30, (src.name, db)
        else:  # subtracted with a fitted flux: measured -32.6 (Vir A) and -30.1 dB (Tau A)
            assert db < -28, (src.name, db)


def test_chain_wrote_solutions_and_never_rewrote_the_data(maps):
    d = maps["dir"] / "chain"
    g = zarr.open_group(str(d / "gains.zarr"), mode="r")
    assert g["converged"][:].all()
    assert not g["flags"][:].any()
    p = zarr.open_group(str(d / "peel.zarr"), mode="r")
    mode = p["mode"][:]  # (time, freq, src, pol)
    assert (mode == 1).any() and (mode == 2).any()  # peeled and subtracted
    faint = [p.attrs["sources"].index(n) for n in FAINT]
    assert set(np.unique(mode[:, :, faint])) <= {0, 3}  # the fainter sources only modelled (or set)
    # the flux scale: the removed sources from their peel solutions, the modelled ones from the map
    import json

    rows = {r["name"]: r for r in json.loads((d / "maps" / "fluxscale.json").read_text())}
    assert all(rows[n]["method"].startswith("peel") for n in BRIGHT)
    assert all(rows[n]["method"] == "map" for n in FAINT if n in rows) and "3C 123" in rows
    t = zarr.open_group(str(d / "terrestrial.zarr"), mode="r")
    assert np.abs(t["patterns"][:]).max() > 0
    v = zarr.open_group(str(d / "vis.zarr"), mode="r")
    assert v.attrs["pols"] == ["xx", "yy"]
    # calibrate.flag_autos: the autocorrelations are kept in vis.zarr but carry no imaging weight
    pairs = v["pairs"][:]
    autos = pairs[:, 0] == pairs[:, 1]
    assert (v["weights"][:, autos] > 0).all()
    inv_var = zarr.open_group(str(d / "mmodes.zarr"), mode="r")["inv_var"][:]
    assert (inv_var[:, autos] == 0).all() and (inv_var[:, ~autos] > 0).all()


class Crash(BaseException):
    pass


def test_killed_peel_stage_resumes_bit_identical(maps, tmp_path, monkeypatch):
    """A driver killed after the first peel task resumes: every solution store and the m-modes are
    bit-identical to the uninterrupted chain's. The run starts from the chain's simulated and
    calibrated data (:func:`tests.workflow_helpers.fork_run`) and resumes up to the m-modes, the
    last store compared."""
    from mmflow.workflow.pipeline import ORDER
    from mmflow.workflow.engine.rundir import RunDir

    real = RunDir.mark_done
    seen = []

    def die_after_first_peel_task(self, stage, key, info, chunks):
        real(self, stage, key, info, chunks)
        if stage == "peel" and not key.startswith("_"):
            seen.append(key)
            raise Crash()

    run = fork_run(maps["dir"] / "chain", tmp_path / "run", "calibrate")
    cfg = load_config(DEMO, BASE + [f"run.directory={run}"])
    monkeypatch.setattr(RunDir, "mark_done", die_after_first_peel_task)
    with pytest.raises(Crash):
        run_workflow(cfg, **QUIET)
    monkeypatch.setattr(RunDir, "mark_done", real)
    summaries = run_workflow(cfg, only=ORDER[:ORDER.index("mmodes") + 1], **QUIET)
    assert seen == [seen[0]] and summaries["peel"]["tasks_run"] == summaries["peel"]["tasks"] - 1
    ref = maps["dir"] / "chain"
    for store in ("gains.zarr", "peel.zarr", "terrestrial.zarr", "mmodes.zarr"):
        a, b = zarr.open_group(str(ref / store), mode="r"), zarr.open_group(str(run / store), mode="r")
        for name, arr in a.arrays():
            assert np.array_equal(arr[:], b[name][:], equal_nan=True), (store, name)


def test_dd_solution_interval_shares_the_screen_and_keeps_the_map(maps, tmp_path):
    """``peel.solint_s`` of 4 integrations with per-antenna DD gains: within each interval the stored
    DD gains of a peeled source are one antenna vector times a real amplitude per integration (the
    interval model ``sqrt(a(t)) p``), and the map stays close to the clean sky (measured 2.93 K
    against the demo's 2.61 K with the screen per integration, 1.12x: the simulated refraction
    varies on 5-20 min; docs/calibration.md)."""
    import shutil

    run = tmp_path / "solint"
    shutil.copytree(maps["dir"] / "chain", run)
    cfg = load_config(DEMO, BASE + [f"run.directory={run}", "peel.solint_s=336.6", "peel.dd_model=antenna"])
    run_workflow(cfg, force=True, **QUIET)  # simulate and calibrate are kept; peel onwards recomputed
    p = zarr.open_group(str(run / "peel.zarr"), mode="r")
    h, mode = p["dd_gains"][:, 0], p["mode"][:, 0]  # (time, src, ant, pol), (time, src, pol)
    checked = 0
    for t0 in range(0, h.shape[0], 4):
        for s in range(h.shape[1]):
            for q in range(h.shape[3]):
                peeled = np.flatnonzero(mode[t0:t0 + 4, s, q] == 1)
                if len(peeled) < 2 or p["guard"][t0:t0 + 4, 0, s, q].any():
                    continue
                g = h[t0 + peeled, s, :, q]
                ratio = g / g[:1]  # the same p: a real positive factor per integration, equal for all antennas
                assert np.abs(ratio - ratio[:, :1]).max() < 1e-9 and np.abs(ratio.imag).max() < 1e-9
                checked += 1
    assert checked > 100
    seen = maps["truth"] != healpy.UNSEEN
    diff = np.std((_map(run) - maps["truth"])[seen])
    base = np.std((maps["chain"] - maps["truth"])[seen])
    print(f"map difference rms: DD interval 4 integrations {diff:.4g} K, per integration {base:.4g} K")
    assert diff < 1.5 * base


def test_terrestrial_stage_without_a_terrestrial_signal_leaves_the_map(maps, tmp_path):
    """No cross-talk or RFI in the data (noiseless, DD effects only, so no gain calibration either;
    per-antenna DD gains warm-started, which leave more of the peeled sources than the default screen): the
    template the stage fits to the zenith-phased average is then the residual sky's m = 0 part.
    Fitted on every cross baseline and subtracted per integration, it changes the map by less than
    the thermal noise (measured 0.42 K against 1.90 K: what the per-integration amplitude fit takes
    of the sky). Fitted on baselines > 2 wavelengths only and subtracted on all, it put up to
    1.7e4 Jy on the short baselines it was never fitted on: 357 K of map change."""
    import shutil

    run = tmp_path / "noxt"
    # warm-started per-antenna DD gains leave more of the peeled sources in the average: a rougher m = 0 part
    quiet = ["corrupt.crosstalk_jy=0", "corrupt.gains=false", "corrupt.sawtooth_db=0", "sky.noise=false",
             "peel.warm_start=true", "peel.dd_model=antenna", "calibrate.enabled=false"]
    _run(run, *quiet)
    with_t = _map(run)
    off = tmp_path / "noxt_off"
    shutil.copytree(run, off)
    cfg = load_config(DEMO, BASE + [f"run.directory={off}", *quiet, "terrestrial.enabled=false"])
    run_workflow(cfg, force=True, **QUIET)  # simulate, calibrate and peel kept; m-modes onward recomputed
    seen = maps["truth"] != healpy.UNSEEN
    change = np.std((with_t - _map(off))[seen])
    noise_rms = np.std((maps["noisy"] - maps["truth"])[seen])
    print(f"terrestrial stage on data without a terrestrial signal: map change {change:.4g} K rms, "
          f"thermal-noise map {noise_rms:.4g} K")
    assert change < noise_rms


def test_cas_a_flux_measured_against_cyg_a(maps, tmp_path):
    """``calibrate.measure_flux: [Cas A]`` (the paper's recipe): Cyg A alone sets the flux scale and
    Cas A's flux over its catalogue model is measured per solution interval (``gains.zarr``
    ``flux_factor``). The simulated Cas A has its catalogue flux, so the measurements scatter about
    1 by the scintillation's finite-sample means (sigma 0.17 at 40 MHz over 7 integrations; measured:
    median 1.0000, scatter 0.12 over 294 interval-pols); the unscreened sources keep 1 and Cyg A's
    factor is 1 in every interval (by construction: its mean sets the scale)."""
    run = fork_run(maps["dir"] / "chain", tmp_path / "measure", "simulate")
    cfg = load_config(DEMO, BASE + [f"run.directory={run}", "calibrate.measure_flux=[Cas A]"])
    summary = run_workflow(cfg, only=["calibrate"], **QUIET)
    assert summary["calibrate"]["counts"]["screened_integrations"] > 1000  # both sources, 2 pols, where up
    g = zarr.open_group(str(run / "gains.zarr"), mode="r")
    names = list(g.attrs["sources"])
    f = g["flux_factor"][:, 0]  # (interval, source, pol)
    cyg, cas = f[:, names.index("Cyg A")], f[:, names.index("Cas A")]
    cas_up = cas[cas > 0]  # 0: Cas A below the horizon
    print(f"Cas A measured: median {np.median(cas_up):.4f}, scatter {np.std(cas_up):.4f} over {cas_up.size} "
          f"interval-pols; Cyg A mean {np.mean(cyg[cyg > 0]):.4f}")
    assert cas_up.size > 100
    assert abs(np.median(cas_up) - 1) < 0.02
    assert np.allclose(cyg[cyg > 0], 1)
    others = [k for k, n in enumerate(names) if n not in ("Cyg A", "Cas A")]
    assert (f[:, others] == 1).all()
