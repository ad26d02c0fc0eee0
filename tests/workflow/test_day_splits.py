"""Per-day and day/night data splits (issue 11, section 3: "with more than one day, day/night and
per-day splits too").

Kernels: the sidereal day of each integration, the Sun's elevation against the Astronomical
Almanac's low-precision solar position, the per-day jackknife against a Monte Carlo of the map
noise (equal and unequal days). Workflow: noiseless data of three sidereal days (every day sees
the same sky, so each day's m-modes are the full m-modes); pure thermal noise over three days
(the per-day jackknife sigma against a Monte Carlo of the map noise, beside the even/odd one,
and as the clean stage's threshold when even/odd are absent); the refusals.
"""
import json
import shutil

import healpy
import numpy as np
import pytest
import zarr

from mmflow.conventions import healpy_alm
from mmflow.errors import InputError
from mmflow.imaging import clean as ck
from mmflow.imaging import jackknife
from mmflow.mmode import splits as sp
from mmflow.workflow.engine.runner import run_workflow
from mmflow.workflow.engine import clean_state as cs
from tests.imaging_helpers import Imager
from tests.workflow_helpers import SMALL, refused_problem, small_config

QUIET = dict(progress=False, log=lambda *a: None)
T_SID = 86164.0905
DAYS3 = ["observation.n_integrations=750", "sky.diffuse=false", "sky.sources=[Cyg A]",
         "transfer.noise_weighting=false", "products.png=false", "clean.min_separation_deg=15", "clean.max_cycles=2"]
LMAX = 24


# ----------------------------------------------------------------------------- kernels

def test_day_index_counts_sidereal_days_from_the_first_lst_across_gaps():
    tau = T_SID / 100
    k = np.concatenate([np.arange(0, 130), np.arange(260, 300)])  # a gap of more than a day
    lst = np.mod(1.0 + 2 * np.pi * k * tau / T_SID, 2 * np.pi)
    t = 2457802.0 + k * tau / 86400.0
    np.testing.assert_array_equal(sp.day_index(lst, t), k // 100)
    # the turnover is where the LST passes the first integration's, not at LST 0 (here 1 rad)
    assert sp.day_index(lst, t)[99] == 0 and sp.day_index(lst, t)[100] == 1
    # without times the unwrapped LSTs cannot see the skipped day
    assert sp.day_index(lst)[-1] == 1


def _almanac_sun_elevation_deg(jd, lat_deg, lon_deg):
    """The Astronomical Almanac's low-precision Sun (~0.01 deg, 1950-2050) and GMST: independent of astropy."""
    n = jd - 2451545.0
    g = np.deg2rad(357.528 + 0.9856003 * n)
    lam = np.deg2rad(280.460 + 0.9856474 * n + 1.915 * np.sin(g) + 0.020 * np.sin(2 * g))
    eps = np.deg2rad(23.439 - 4e-7 * n)
    ra = np.arctan2(np.cos(eps) * np.sin(lam), np.cos(lam))
    dec = np.arcsin(np.sin(eps) * np.sin(lam))
    lst = np.deg2rad(15 * (18.697374558 + 24.06570982441908 * n) + lon_deg)
    phi = np.deg2rad(lat_deg)
    return np.rad2deg(np.arcsin(np.sin(phi) * np.sin(dec) + np.cos(phi) * np.cos(dec) * np.cos(lst - ra)))


def test_day_night_masks_follow_the_suns_elevation_at_the_site():
    lat, lon = 37.2398, -118.2817  # OVRO-LWA
    jd = 2457802.0 + np.linspace(-0.5, 0.5, 49)  # 2017-02-17 12:00 .. 02-18 12:00 UTC
    jd = np.concatenate([jd, [2457926.3 + 0.5 / 24]])  # 2017-06-21 19:30 UTC: near local noon in June
    el = sp.sun_elevation_deg(jd, lat, lon, 1222.0)
    ref = _almanac_sun_elevation_deg(jd, lat, lon)
    print("max |astropy - almanac| elevation (deg)", np.abs(el - ref).max())
    assert np.abs(el - ref).max() < 0.05
    assert el[-1] == pytest.approx(90 - lat + 23.44, abs=0.5)  # the June Sun at upper culmination
    masks = sp.split_masks(["full", "day", "night"], sun_elevation=el)
    assert set(masks) == {"day", "night"}
    clear = np.abs(ref) > 0.05  # away from the horizon, where the two may round either way
    assert clear.sum() >= 48
    np.testing.assert_array_equal(masks["day"][clear], (ref > 0)[clear])
    np.testing.assert_array_equal(masks["night"], ~masks["day"])
    assert 0.3 < masks["day"][:49].mean() < 0.6  # a February day at +37 deg: ~11 h of Sun
    # many times: astropy on a 300 s grid, interpolated
    many = 2457802.0 + np.arange(1500) * 61.0 / 86400.0
    fast = sp.sun_elevation_deg(many, lat, lon, 1222.0)
    assert np.abs(fast - _almanac_sun_elevation_deg(many, lat, lon)).max() < 0.02
    assert np.abs(fast[::50] - sp.sun_elevation_deg(many[::50], lat, lon, 1222.0)).max() < 0.005


@pytest.mark.parametrize("start", [0.0, 0.3, 1.0, 2.0, 5.5, 6.28])
def test_day_index_splits_a_regular_grid_into_whole_days_for_any_start_lst(start):
    """Three days of 250 integrations: one LST a whole turn after the first is ``phi_0 + 2 pi`` up to
    rounding, and must start the next day (not end this one: start 0.3 gave [251, 249, 250]). The
    times of the simulation (apparent LST, pyuvdata), the config check's sidereal-rate times and
    the unwrapped LSTs all give the same days."""
    from types import SimpleNamespace

    from mmflow.simulate.corrupt import utc_at_lsts
    from mmflow.conventions import drift_scan_lsts

    lst = np.asarray(drift_scan_lsts(start, T_SID / 250, np.arange(750)))
    site = SimpleNamespace(lat_deg=37.2398, lon_deg=-118.2817, height_m=1222.0)
    stage = sp.day_index(lst, utc_at_lsts(lst, site, 2457802.0))  # what the mmodes stage sees
    np.testing.assert_array_equal(stage, np.arange(750) // 250)
    np.testing.assert_array_equal(sp.day_index(lst, sp.sidereal_times_jd(lst, 2457802.0)), stage)  # config check
    np.testing.assert_array_equal(sp.day_index(lst), stage)
    assert [sp.bin_coverage(lst[stage == j], 250) for j in range(3)] == [1.0, 1.0, 1.0]


def test_day_index_counts_from_the_earliest_time_whatever_the_row_order():
    k = np.arange(750)
    lst, t = np.mod(0.3 + 2 * np.pi * k / 250, 2 * np.pi), 2457802.0 + k * T_SID / 250 / 86400.0
    perm = np.r_[10:750, 0:10]  # the first rows are not the earliest
    np.testing.assert_array_equal(sp.day_index(lst[perm], t[perm]), (k // 250)[perm])


def test_split_problems_name_the_split_and_the_reason():
    lst = np.mod(2 * np.pi * np.arange(250) / 100, 2 * np.pi)  # 2.5 days of 100 bins
    days = sp.day_index(lst)
    probs = {name: problem for name, problem, _ in sp.split_problems(["full", "day1", "day2", "day3"], lst, days,
                                                                        None, 100, 0.95)}
    assert set(probs) == {"day2", "day3"}
    assert "whole days" in probs["day2"] and "50.0%" in probs["day2"]
    assert "3 sidereal days (day0 .. day2), no day3" in probs["day3"]
    sun = np.where(np.arange(250) % 100 < 50, 10.0, -10.0)  # the Sun up at the same LSTs every day
    (name, problem, fix), = sp.split_problems(["full", "night"], lst, days, sun, 100, 0.95)
    assert name == "night" and "months" in fix


def test_a_partial_day_is_refused_even_when_not_listed():
    """1.5 days: the half day is in the full data, so day0 alone is no whole-day jackknife (a Monte
    Carlo of [full, day0] here gives sigma ~19 % low); refused naming the partial day, listed or not."""
    k = np.arange(375)
    lst, t = np.mod(0.3 + 2 * np.pi * k / 250, 2 * np.pi), 2457802.0 + k * T_SID / 250 / 86400.0
    days = sp.day_index(lst, t)
    for names in (["full", "day0"], ["full", "day0", "day1"]):
        (name, problem, fix), = sp.split_problems(names, lst, days, None, 250, 0.95)
        assert name == "day1" and "day1 fills 50.0% of the 250 sidereal bins" in problem
        assert "per-day jackknife needs whole days" in problem and "whole sidereal days" in fix and "even/odd" in fix
    assert sp.split_problems(["full", "even", "odd"], lst, days, None, 250, 0.95) == []  # no day<k>: no day check


def test_days_after_a_gap_are_named():
    """Days 0-2 and 150-152 (a gap of months): day150 is a day of the data, day3 is named absent, not partial."""
    k = np.concatenate([np.arange(0, 750), np.arange(150 * 250, 153 * 250)])
    lst, t = np.mod(0.3 + 2 * np.pi * k / 250, 2 * np.pi), 2457802.0 + k * T_SID / 250 / 86400.0
    days = sp.day_index(lst, t)
    assert sorted(set(days)) == [0, 1, 2, 150, 151, 152]
    assert sp.split_problems(["full", "day0", "day150"], lst, days, None, 250, 0.95) == []
    (name, problem, fix), = sp.split_problems(["full", "day0", "day3"], lst, days, None, 250, 0.95)
    assert name == "day3" and "6 sidereal days (day0 .. day2, day150 .. day152), no day3" in problem
    assert "day0 .. day2, day150 .. day152" in fix and "partial" not in problem


def test_split_shares_count_the_flags():
    """f_k from unflagged samples: day2 half flagged gives 0.4 / 0.4 / 0.2, not 1/3 each."""
    f = sp.split_shares([1250, 500, 500, 250], ["full", "day0", "day1", "day2"])
    assert f == {"full": 1.0, "day0": 0.4, "day1": 0.4, "day2": 0.2}


def test_day_night_map_has_the_full_maps_noise_for_any_shares():
    """A sky both halves see plus noise of variance sigma^2 / f per half (inverse-variance weights):
    sqrt(f_d f_n) (day - night) cancels the sky and has the rms sigma_all for equal and unequal
    halves; the plain half-difference would be 1.09 sigma_all for 0.3 / 0.7; the mean has the sky."""
    rng = np.random.default_rng(5)
    n, sigma = 400_000, 2.0
    sky = 100 * rng.normal(size=n)
    for f_d in (0.5, 0.3):
        f_n = 1 - f_d
        day, night = sky + sigma / np.sqrt(f_d) * rng.normal(size=n), sky + sigma / np.sqrt(f_n) * rng.normal(size=n)
        dn = jackknife.day_night_difference(day, night, f_d, f_n)
        assert jackknife.masked_rms(dn) == pytest.approx(sigma, rel=0.01)
        assert np.sqrt(np.mean((0.5 * (day - night)) ** 2)) == pytest.approx(sigma / np.sqrt(4 * f_d * f_n), rel=0.01)
    with pytest.raises(InputError, match="shares"):
        jackknife.day_night_difference(day, night, 1.0, 0.0)


@pytest.mark.parametrize("day_weights", [(1, 1, 1), (1, 1, 0.5)])
def test_per_day_jackknife_matches_a_monte_carlo_of_the_map_noise(blocks, small_telescope, day_weights):
    """D = 3 days on one sidereal grid (a bright sky that every day sees, plus noise of variance
    ``sigma^2 / w_k``); the full data are the inverse-variance weighted mean of the days; the
    per-day jackknife with ``f_k = w_k / sum w`` against 60 Monte Carlo maps of the full data's noise."""
    from mmflow.mmode.transform import mmode_transform
    from mmflow.sky.diffuse import band_limited_random_alm
    from tests.imaging_helpers import to_time

    eps = 1e-3 * max(np.linalg.eigvalsh(b.conj().T @ b)[-1] for b in blocks.values())
    imager, mask = Imager(blocks, eps), ck.observed_mask(16, ck.never_seen_dec_min(small_telescope.lat_rad))
    n_bins, sigma, nb = 4 * LMAX + 8, 3.0, blocks[0].shape[0]
    w = np.asarray(day_weights, float)
    f = w / w.sum()
    rng = np.random.default_rng(11)

    def day_noise():
        return [sigma / np.sqrt(wk) * (rng.normal(size=(n_bins, nb)) + 1j * rng.normal(size=(n_bins, nb))) / np.sqrt(2)
                for wk in w]

    mc = np.array([imager.map(mmode_transform(sum(fk * n for fk, n in zip(f, day_noise())), LMAX))
                   for _ in range(60)])
    var_mc = np.mean(np.var(mc, axis=0, ddof=1)[mask])
    signal = to_time(blocks, 50 * band_limited_random_alm(LMAX, seed=2), n_bins)
    jk = []
    for _ in range(20):
        days = [signal + n for n in day_noise()]
        full = imager.map(mmode_transform(sum(fk * d for fk, d in zip(f, days)), LMAX))
        jk.append(jackknife.per_day_variance(full, [imager.map(mmode_transform(d, LMAX)) for d in days], f, mask))
    ratio = np.sqrt(np.mean(jk) / var_mc)
    print("per-day jackknife / MC sigma", day_weights, ratio)
    assert ratio == pytest.approx(1.0, abs=0.05)
    if day_weights[-1] != 1:  # ignoring the unequal weights (1 / (D - 1)) is biased
        naive = [jackknife.per_day_variance(full, [imager.map(mmode_transform(d, LMAX)) for d in days],
                                            np.full(3, 1 / 3), mask)]
        assert naive[0] != pytest.approx(jk[-1], rel=0.05)


def test_two_equal_days_give_the_even_odd_formula():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=500), rng.normal(size=500)
    full = 0.5 * (a + b)
    assert jackknife.per_day_variance(full, [a, b], [0.5, 0.5]) == pytest.approx(
        jackknife.jackknife_variance(full, a, b), rel=1e-14)
    np.testing.assert_allclose(jackknife.noise_realisation({"full": full, "day0": a}, "per_day", {"day0": 0.5}),
                               a - full)
    with pytest.raises(InputError, match="share"):
        jackknife.per_day_variance(full, [a], [1.0])
    with pytest.raises(ValueError, match="unknown jackknife"):
        jackknife.noise_realisation({"full": full, "day0": a}, "bogus", {"day0": 0.5})


# ----------------------------------------------------------------------------- workflow

@pytest.fixture(scope="module")
def three_days(tmp_path_factory):
    """Noiseless and noisy runs of the same three sidereal days (250 integrations a day)."""
    root = tmp_path_factory.mktemp("days")
    runs = {}
    for name, extra in [("noiseless", ["sky.noise=false", "mmode.splits=[full, day0, day1, day2]"]),
                        ("noisy", ["sky.noise=true", "mmode.splits=[full, day0, day1, day2, even, odd]",
                                   "clean.enabled=true"]),
                        ("noisy_days", ["sky.noise=true", "mmode.splits=[full, day0, day1, day2]", "clean.enabled=true",
                                        "clean.threshold_sigma=4"])]:
        cfg = small_config(root / name, *DAYS3, *extra, "run.keep=[mmodes.zarr]")
        run_workflow(cfg, **QUIET)
        runs[name] = (root / name, cfg)
    return runs


def _alm(run_dir):
    return zarr.open_group(str(run_dir / "alm.zarr"), mode="r")["alm"][:, 0]


def _seen(run_dir, nside):
    lat = np.deg2rad(zarr.open_group(str(run_dir / "vis.zarr"), mode="r").attrs["lat_deg"])
    return ck.observed_mask(nside, ck.never_seen_dec_min(lat))


def test_each_day_of_noiseless_data_has_the_full_mmodes(three_days):
    run_dir, _ = three_days["noiseless"]
    g = zarr.open_group(str(run_dir / "mmodes.zarr"), mode="r")
    mm = g["mmodes"][:]
    assert g.attrs["splits"] == ["full", "day0", "day1", "day2"] and g.attrs["n_days"] == 3
    assert g.attrs["days"] == [0, 1, 2] and "split_weights" not in g.attrs
    n = g["n_samples"][:]  # every integration unflagged: 750 and 250 a day on every baseline
    assert (n[0] == 750).all() and (n[1:] == 250).all()
    scale = np.abs(mm[0]).max()
    for k in (1, 2, 3):
        assert np.abs(mm[k] - mm[0]).max() < 1e-12 * scale
    alm = _alm(run_dir)
    assert np.abs(alm[1:] - alm[0]).max() < 1e-10 * np.abs(alm[0]).max()


def test_per_day_jackknife_on_pure_noise_matches_a_monte_carlo(three_days):
    """The noise of each day's map (noisy - noiseless, same operator) is an independent draw of
    D times the full map's noise variance: a 3-draw Monte Carlo of the map noise. The per-day and
    the even/odd jackknife sigma of the noisy run (products' ``noise.by_split``) match it within 5 %."""
    (q_dir, cfg), (n_dir, _) = three_days["noiseless"], three_days["noisy"]
    nside = cs.clean_nside(cfg)
    seen = _seen(n_dir, nside)
    alm_q, alm_n = _alm(q_dir), _alm(n_dir)

    def noise_map(k):  # split k of both runs (the same first four splits)
        return healpy.alm2map(healpy_alm(alm_n[k] - alm_q[k], LMAX, LMAX), nside, lmax=LMAX)

    sigma_mc = np.sqrt(np.mean([np.mean(noise_map(k)[seen] ** 2) for k in (1, 2, 3)]) / 3)
    summ = json.loads((n_dir / "maps" / "summary_40.000MHz.json").read_text())
    by = summ["noise"]["by_split"]
    ratios = {k: by[k]["jy_per_sr"] / sigma_mc for k in ("per_day", "even_odd")}
    full = np.sqrt(np.mean(noise_map(0)[seen] ** 2))  # the full map's one realisation
    print("jackknife / Monte Carlo sigma", ratios, "full map's realisation / MC", full / sigma_mc)
    for r in ratios.values():
        assert r == pytest.approx(1.0, abs=0.05)
    assert full == pytest.approx(sigma_mc, rel=0.1)
    # Table 1 carries both beside the paper's column (even/odd: the paper's estimator)
    row = summ["table1"]
    assert summ["noise"]["estimator"] == "even_odd" and row["noise_k"] == row["noise_k_even_odd"]
    assert row["noise_k_per_day"] == pytest.approx(by["per_day"]["kelvin"], rel=1e-12)
    md = (n_dir / "maps" / "table1.md").read_text()
    assert "per-day (K)" in md and "even/odd (K)" in md
    assert "noise_k_per_day" in (n_dir / "maps" / "table1.csv").read_text().splitlines()[0]


def test_clean_threshold_uses_the_per_day_jackknife_without_even_odd(three_days):
    run_dir, cfg = three_days["noisy_days"]
    nside = cs.clean_nside(cfg)
    alm = _alm(run_dir)
    maps = {s: healpy.alm2map(healpy_alm(alm[k], LMAX, LMAX), nside, lmax=LMAX)
            for k, s in enumerate(cfg.mmode.splits)}
    sigma = np.sqrt(jackknife.per_day_variance(maps["full"], [maps[f"day{k}"] for k in range(3)], [1 / 3] * 3,
                                               _seen(run_dir, nside)))
    g = zarr.open_group(str(run_dir / "clean.zarr"), mode="r")
    assert float(g["noise"][0, 0]) == pytest.approx(sigma, rel=1e-9)
    assert float(g["threshold"][0]) == pytest.approx(4 * sigma, rel=1e-9)
    summ = json.loads((run_dir / "maps" / "summary_40.000MHz.json").read_text())
    assert summ["noise"]["estimator"] == "per_day" and "even_odd" not in summ["noise"]["by_split"]
    noise_map = healpy.read_map(str(run_dir / summ["images"]["noise"]["fits"]))  # sqrt(f/(1-f)) (day0 - all)
    seen = noise_map != healpy.UNSEEN
    assert np.sqrt(np.mean(noise_map[seen] ** 2)) == pytest.approx(summ["noise"]["kelvin"], rel=0.15)


def test_day_night_map_and_report_line(tmp_path):
    """One day split at the horizon (a low min_coverage lets the halves through: the workflow path,
    not a jackknife): the systematics map (day - night) / 2 in maps/, its rms in Table 1 and the report."""
    cfg = small_config(tmp_path / "dn", "sky.diffuse=false", "sky.sources=[Cyg A]", "products.nside=16",
                       "mmode.splits=[full, even, odd, day, night]", "mmode.min_coverage=0.3", "clean.enabled=true",
                       "clean.min_separation_deg=15", "clean.max_cycles=1", "transfer.noise_weighting=false")
    run_workflow(cfg, **QUIET)
    summ = json.loads((tmp_path / "dn" / "maps" / "summary_40.000MHz.json").read_text())
    img = summ["images"]["daynight"]
    dn = healpy.read_map(str(tmp_path / "dn" / img["fits"]))
    assert np.isclose(img["rms_observed"], dn[dn != healpy.UNSEEN].std())
    # the shares from the Sun at the simulation's times, independently of the stage's counts
    v = zarr.open_group(str(tmp_path / "dn" / "vis.zarr"), mode="r")
    el = sp.sun_elevation_deg(v["time_jd"][:], v.attrs["lat_deg"], v.attrs["lon_deg"], v.attrs.get("height_m", 0.0))
    f_day = float(np.mean(el > 0))
    n = zarr.open_group(str(tmp_path / "dn" / "mmodes.zarr"), mode="r")["n_samples"][:, 0]  # split, baseline
    assert 0.3 < f_day < 0.6 and n[3].sum() / n[0].sum() == pytest.approx(f_day, rel=1e-12)
    assert (n[3] + n[4] == n[0]).all() and (n[1] + n[2] == n[0]).all()
    # its rms: sqrt(f_d f_n) (day - night) of alm.zarr on the clean stage's pixels and mask
    alm = _alm(tmp_path / "dn")
    nside = cs.clean_nside(cfg)
    diff = np.sqrt(f_day * (1 - f_day)) * (alm[3] - alm[4])
    rms = np.sqrt(np.mean(healpy.alm2map(healpy_alm(diff, LMAX, LMAX), nside, lmax=LMAX)[_seen(tmp_path / "dn",
                                                                                                  nside)] ** 2))
    assert summ["noise"]["by_split"]["day_night"]["jy_per_sr"] == pytest.approx(rms, rel=1e-9)
    assert summ["table1"]["noise_k_day_night"] == summ["noise"]["by_split"]["day_night"]["kelvin"] > 0
    html = (tmp_path / "dn" / "maps" / "report.html").read_text()
    assert "day/night systematics sqrt(f_d f_n) (day - night)" in html and "not a noise estimate" in html


def test_refusals_name_the_splits_field(tmp_path):
    (what, field, problem, fix), _ = refused_problem(SMALL + DAYS3 + ["mmode.splits=[full, day3]"], "mmode.splits")
    assert "3 sidereal days" in problem and "day0 .. day2" in fix
    # 1.5 days: [full, day0] is refused too, naming the half day (the jackknife needs whole days)
    (_, _, problem, fix), _ = refused_problem(SMALL + DAYS3 + ["observation.n_integrations=375",
                                                               "mmode.splits=[full, day0]"], "mmode.splits")
    assert "day1 fills 50.0%" in problem and "whole days" in problem and "even/odd" in fix
    (_, _, problem, _), _ = refused_problem(["mmode.splits=[full, day-1]"], "mmode.splits")
    assert "unknown split" in problem
    (_, _, problem, _), _ = refused_problem(SMALL + DAYS3 + ["mmode.splits=[full, day0, day0]"], "mmode.splits")
    assert "once" in problem
    (_, _, problem, fix), _ = refused_problem(["mmode.splits=[full]", "clean.enabled=true"], "clean.threshold")
    assert "day<k>" in problem
    # night on one day of data: refused by the mmodes stage before any task (the data decide it)
    cfg = small_config(tmp_path / "night", "sky.diffuse=false", "sky.sources=[Cyg A]",
                       "mmode.splits=[full, night]")
    with pytest.raises(InputError) as err:
        run_workflow(cfg, only=["simulate", "mmodes"], **QUIET)
    assert err.value.field == "mmode.splits" and "months" in err.value.fix
    assert not (tmp_path / "night" / "mmodes.zarr" / "mmodes").exists()
    shutil.rmtree(tmp_path / "night")


def _flagging(rows_flagged):
    """A ``read_block`` for the mmodes stage that flags the integrations ``rows_flagged(k)`` (bool of the
    row index): flags as the stage sees them after ingest or calibration (weights 0)."""
    from mmflow.workflow.stages.mmodes import stage as ms

    read = ms.read_block

    def read_flagged(ctx, rows=slice(None), columns=slice(None), **kw):
        block = read(ctx, rows, columns, **kw)
        k = np.arange(*block.rows.indices(block.rows.stop))
        block.weights[rows_flagged(k)] = 0.0
        return block

    return read_flagged


def test_a_half_flagged_day_has_the_share_of_its_unflagged_samples(tmp_path):
    """Day 2 with every other integration flagged (RFI; 83 bins of ~3 integrations: every bin still holds data):
    the shares f_k come from the flags, 0.4 / 0.4 / 0.2 (the LSTs alone say 1/3 each: on noise alone
    the jackknife variance would be 1.175x too high), and the clean stage's per-day sigma uses them.
    (That the estimator with these shares is unbiased is the Monte Carlo test above, weights 1, 1, 0.5.)"""
    from mmflow.workflow.stages.mmodes import stage as ms

    cfg = small_config(tmp_path / "flag", *DAYS3, "sky.noise=true", "mmode.splits=[full, day0, day1, day2]",
                       "mmode.n_bins=83", "clean.enabled=true")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ms, "read_block", _flagging(lambda k: (k >= 500) & (k % 2 == 0)))
        run_workflow(cfg, **QUIET)
    run_dir = tmp_path / "flag"
    n = zarr.open_group(str(run_dir / "mmodes.zarr"), mode="r")["n_samples"][:, 0]
    assert (n[0] == 625).all() and (n[1] == 250).all() and (n[2] == 250).all() and (n[3] == 125).all()
    nside = cs.clean_nside(cfg)
    alm, seen = _alm(run_dir), _seen(run_dir, nside)
    maps = [healpy.alm2map(healpy_alm(alm[k], LMAX, LMAX), nside, lmax=LMAX) for k in range(4)]
    sigma = np.sqrt(jackknife.per_day_variance(maps[0], maps[1:], [0.4, 0.4, 0.2], seen))
    naive = np.sqrt(jackknife.per_day_variance(maps[0], maps[1:], [1 / 3] * 3, seen))
    noise = float(zarr.open_group(str(run_dir / "clean.zarr"), mode="r")["noise"][0, 0])
    print("per-day sigma with flag shares / with LST shares", sigma / naive)
    assert noise == pytest.approx(sigma, rel=1e-9) and noise != pytest.approx(naive, rel=0.01)


def test_a_flagged_day_is_refused_not_imaged_as_zero(tmp_path):
    """Day 1 entirely flagged: its m-modes would be exactly 0 (then sigma^2 is the whole sky and CLEAN
    stops at once); the mmodes stage refuses it, naming the split and mmode.splits."""
    from mmflow.errors import CoverageError
    from mmflow.workflow.stages.mmodes import stage as ms

    cfg = small_config(tmp_path / "gone", *DAYS3, "mmode.splits=[full, day0, day1, day2]")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ms, "read_block", _flagging(lambda k: (k >= 250) & (k < 500)))
        with pytest.raises(CoverageError) as err:
            run_workflow(cfg, only=["simulate", "mmodes"], **QUIET)
    assert err.value.field == "mmode.splits" and "'day1'" in err.value.problem and "0.0%" in err.value.problem
    assert "remove day1" in err.value.fix


def test_split_masks_cache_is_safe_across_threads(monkeypatch):
    """Two threads asking for different splits: one must not clear the single-entry cache between the
    other's store and its read (a KeyError without the lock)."""
    import threading
    import time

    from mmflow.workflow.stages.mmodes import stage as ms

    class SlowDict(dict):
        def __setitem__(self, key, value):
            super().__setitem__(key, value)
            time.sleep(0.05)  # widen the window between storing an entry and reading it back

    monkeypatch.setattr(ms, "_MASKS", SlowDict())
    k = np.arange(750)
    arrays = {"lst": np.mod(0.3 + 2 * np.pi * k / 250, 2 * np.pi), "time_jd": 2457802.0 + k * T_SID / 250 / 86400.0}

    class Vis(dict):
        attrs = {"lat_deg": 37.2, "lon_deg": -118.3}

    vis = Vis(arrays)
    errors, out = [], {}

    def work(splits):
        try:
            out[tuple(splits)] = ms._time_splits(None, vis, splits)[3]
        except Exception as e:  # noqa: BLE001  (the test reports any failure)
            errors.append(e)

    threads = [threading.Thread(target=work, args=(s,)) for s in (["full", "day0"], ["full", "day1"])]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert out[("full", "day0")]["day0"].sum() == 250 and out[("full", "day1")]["day1"][250:500].all()
