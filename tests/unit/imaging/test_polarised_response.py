"""Whether an array measures polarisation (issue 39 item 2, in part): the resolution matrix at test
sources (:func:`mmflow.imaging.polarised.polarisation_response`) against independently simulated data.

The data: three partially polarised sources written by tests/polarised_fields.py (real fields in the
time domain, nothing of mmflow's simulator), the scene of tests/unit/test_polarised_imaging.py (20
antennas within 12 m, 40 MHz, short dipoles with a cos^3 taper, 300 integrations). The response at a
declination predicts the fractions the solve images for a source there, whatever the data; it calls
polarisation measured only when every fraction comes out within 5 % and an unpolarised source leaks
< 0.5 % of I.
"""
import numpy as np
import pytest

from mmflow.conventions import radec_to_vec
from mmflow.imaging.clean import CleanOptions, restore_map
from mmflow.imaging.polarised import (PolarisedObserver, accumulate_polarised_normal, polarisation_response,
                                      stokes_at, stokes_eps, stokes_maps)
from mmflow.imaging.polarised_clean import (COND_MAX, clean_stokes, close_sources, matrices_at, source_vectors,
                                            stokes_sources)
from mmflow.mmode.polarised import make_polarised_grid
from mmflow.mmode.transfer import baselines_in_wavelengths, fringe_bandlimit
from mmflow.mmode.transform import mmode_transform
from mmflow.telescope import Telescope
from mmflow.telescope.jones import ShortDipoleJones
from mmflow.workflow.stages.solve.settings import ImagingConfig
from tests.polarised_fields import TAPER, correlate
from tests.polarised_scene import FREQ, N_LST, scene_layout

#: (RA deg, Dec offset from the latitude deg, Q/I, U/I, V/I): the response's three test sources, two weakly
#: polarised ones (linear 5 %, V -5 %) and three unpolarised ones (the last transits 47 deg from the zenith)
SOURCES = np.array([[0.0, -20.0, 0.3, -0.2, 0.15], [120.0, 0.0, -0.1, 0.4, -0.1], [240.0, 25.0, 0.2, 0.1, 0.3],
                    [60.0, 15.0, 0.04, -0.03, 0.0], [180.0, -10.0, -0.02, 0.05, -0.05],
                    [320.0, 10.0, 0.0, 0.0, 0.0], [90.0, 35.0, 0.0, 0.0, 0.0], [200.0, -47.0, 0.0, 0.0, 0.0]])
FLUX = np.array([100.0, 80.0, 120.0, 90.0, 110.0, 100.0, 70.0, 100.0])  # Stokes I, Jy


def _normal(lmax, lmax_p=None):
    lay = scene_layout()
    jones = ShortDipoleJones(horizon_taper=TAPER)
    tel = Telescope(lay, jones.power_beam(), [FREQ])
    lst = 2 * np.pi * np.arange(N_LST) / N_LST
    vecs = radec_to_vec(np.deg2rad(SOURCES[:, 0]), np.deg2rad(lay.lat_deg + SOURCES[:, 1]))
    stokes = np.c_[FLUX, FLUX[:, None] * SOURCES[:, 2:]]
    vis = correlate(lay.enu, FREQ, tel.lat_rad, lst, list(zip(stokes, vecs)), tel.antenna_pairs())
    b = baselines_in_wavelengths(tel, tel.antenna_pairs(), FREQ)
    grid = make_polarised_grid(tel.lat_rad, jones, FREQ, lmax, fringe_bandlimit(np.linalg.norm(b, axis=1),
                                                                                  jones.lmax_hint))
    normal = accumulate_polarised_normal(grid, b, mmode_transform(vis, lmax)[None], lmax_p=lmax_p)
    scale = max(np.abs(np.diag(g)).max() for g in normal.gram)
    return normal, scale, vecs, np.deg2rad(lay.lat_deg + SOURCES[:, 1])


@pytest.fixture(scope="module")
def lmax20():
    return _normal(20)


@pytest.fixture(scope="module")
def lmax32():
    return _normal(32)


def _response(fixture, ratio, eps=1e-6):
    normal, scale, vecs, decs = fixture
    observe = PolarisedObserver(normal, (eps * scale, ratio * eps * scale))
    return observe, polarisation_response(observe, decs[:3])  # the three test sources' declinations


@pytest.mark.parametrize("ratio", [1.0, 100.0])
def test_response_predicts_the_fractions_imaged_from_independent_data(ratio, lmax32):
    """At each test source's declination ``ratio_X x`` the true fraction is the fraction imaged from the
    independent data, within 0.015 (measured <= 0.010: the other seven sources' sidelobes and the leakage term,
    read at the source), with equal relative
    eps (1e-6 of the largest Gram diagonal) and with the weakly-polarised prior ``eps_pol = 100 eps``.
    (At lmax 32 the data are inside the model: at lmax 20 the sky the array sees beyond l = 20 is not.)"""
    observe, resp = _response(lmax32, ratio)
    at = stokes_at(observe.solution()[0], lmax32[2][:3], 32)
    for k in range(3):
        got = at[k, 1:] / at[k, 0]
        want = np.array([resp[f"ratio_{x}"][k] for x in "quv"]) * SOURCES[k, 2:]
        print(f"eps_pol / eps {ratio:g}: source {k} fractions {np.round(got, 4)}, response predicts "
              f"{np.round(want, 4)}, true {SOURCES[k, 2:]}; leakage {resp['leakage'][k]:.3%}")
        np.testing.assert_allclose(got, want, atol=0.015)


@pytest.mark.parametrize("lmax, eps, ratio, measured", [(20, 1e-6, 1.0, True), (32, 1e-6, 1.0, True),
                                                         (32, 1e-6, 100.0, False), (32, 1e-2, 1.0, False)])
def test_response_says_whether_the_array_measures_polarisation(lmax, eps, ratio, measured, lmax20, lmax32):
    """With equal relative eps (1e-6 of the largest Gram diagonal) every fraction is imaged within 5 %
    and an unpolarised source leaks < 0.5 % of I: measured (lmax 20: ratios 0.99-1.00, leakage
    <= 0.02 %; lmax 32: 1.000, <= 0.47 %). With the weakly-polarised prior eps_pol = 100 eps (the
    default's ratio) at lmax 32 the fractions come out at 0.75-0.80, and with a strong equal eps
    (1e-2) I leaks into Q, U: not measured, and the note says so."""
    _, resp = _response(lmax20 if lmax == 20 else lmax32, ratio, eps)
    print("\nRESP", lmax, eps, ratio, {k: np.round(resp[k], 4).tolist() for k in ("ratio_q", "ratio_u", "ratio_v",
                                                                                  "leakage")}, resp["note"])
    assert resp["measured"] == measured
    assert ("do not image polarisation as it is" in resp["note"]) == (not measured)


def test_fractions_are_taken_against_i_at_the_polarised_band_limit():
    """With Q, U, V band-limited below I (``imaging.stokes_lmax`` 16 at lmax 32) the response takes each
    fraction against I at the same band limit: ratios 0.985-1.001 (against I at lmax 32 a point source's
    peak alone would make them 0.40-0.43), and with equal relative eps (1e-6) the leakage is <= 0.01 %.
    (On the independent data of this scene the fractions then image at 1.07-1.33 of the truth: the
    polarised sky the array measures between l = 16 and 20 is outside the model and aliases into it,
    docs/stokes.md; so stokes_lmax below the array's resolution does not make polarisation measured.)"""
    normal, scale, vecs, decs = _normal(32, lmax_p=16)
    resp = polarisation_response(PolarisedObserver(normal, (1e-6 * scale, 1e-6 * scale)), decs[:3])
    np.testing.assert_allclose([resp[f"ratio_{x}"] for x in "quv"], 1.0, atol=0.03)
    assert max(resp["leakage"]) < 2e-4


@pytest.fixture(scope="module")
def cleaned(lmax32):
    """The full-Stokes CLEAN of the independent data's solve with the default eps and eps_pol (0.01 and
    100 x 0.01 of Grams whose largest diagonal is 6.6 with unit weights, as the stokes stage's; the m-filters
    off: a noiseless sky), 8 peaks a cycle at loop gain 0.3, to 1 % of the I peak."""
    normal, _, vecs, _ = lmax32
    observe = PolarisedObserver(normal, stokes_eps(ImagingConfig().eps, ImagingConfig().eps_pol))
    dirty = observe.solution()[0]
    lat = np.deg2rad(scene_layout().lat_deg)
    opts = CleanOptions(n_peaks=8, gain=0.3, stall_cycles=0, max_cycles=100)
    peak = np.abs(stokes_at(dirty, vecs, 32)[:, 0]).max()
    result = clean_stokes(observe, dirty, lat, opts, 64, threshold=1e-2 * peak, dec_step_deg=4.0)
    return observe, dirty, result, stokes_sources(result, 32)


def _nearest(sources, vec):
    return sources[int(np.argmax(source_vectors(sources) @ vec))]


def test_clean_gives_each_source_its_stokes_parameters_with_the_default_regularisation(lmax32, cleaned):
    """Issue 39 item 2 on data mmflow did not make (tests/polarised_fields.py): with the default eps and
    eps_pol the maps' fractions are 0.03-0.5 of the truth (the prior shrinks them; the response says so), but
    the CLEAN inverts each source's response: linear fractions within 5 % of the truth (measured <= 0.5 %),
    angles within 2 deg (<= 0.05 deg), V within 5 % (<= 0.6 %), the unpolarised sources' Q, U, V < 0.5 % of I
    (<= 0.03 %), I within 2 % (<= 0.7 %), each source found within 0.1 deg; the source 47 deg from the zenith at
    transit, where cond(A) is ~50 (the maps hold 0.03 of its Q, U, V), is stated as not measured (its I alone,
    within 10 %: measured 2.6 % low, 1.1 deg off)."""
    _, _, vecs, decs = lmax32
    observe, dirty, result, sources = cleaned
    truth = np.c_[FLUX, FLUX[:, None] * SOURCES[:, 2:]]
    dirty_at = stokes_at(dirty, vecs, 32)
    print(f"\n{result['cycles']} cycles, {len(result['stokes'])} components, stop {result['reason']}")
    for k, (vec, t) in enumerate(zip(vecs, truth)):
        src = _nearest(sources, vec)
        off = np.rad2deg(np.arccos(min(1.0, source_vectors([src])[0] @ vec)))
        print(f"source {k} dec {np.rad2deg(decs[k]):5.1f}: cond {src['cond']:6.1f} measured {src['measured']}, "
              f"{off:.3f} deg off; maps' Q, U, V / I {np.round(dirty_at[k, 1:] / dirty_at[k, 0], 4)}; CLEAN "
              f"{np.round(np.array(src['stokes_jy'], float), 3)} true {t}")
        if k == 7:  # 47 deg from the zenith at transit
            assert not src["measured"] and src["cond"] > COND_MAX and src["linear_fraction"] is None
            assert off < 2.0 and abs(src["stokes_jy"][0] / t[0] - 1) < 0.1
            continue
        assert off < 0.1 and abs(src["stokes_jy"][0] / t[0] - 1) < 0.02
        assert src["measured"]
        s = np.array(src["stokes_jy"])
        lin, lin_true = np.hypot(*s[1:3]) / s[0], np.hypot(*t[1:3]) / t[0]
        if lin_true == 0 and t[3] == 0:
            assert np.abs(s[1:]).max() < 0.005 * s[0]
            continue
        assert src["linear_fraction"] == pytest.approx(lin) and abs(lin / lin_true - 1) < 0.05
        chi = src["angle_deg"] - np.rad2deg(0.5 * np.arctan2(t[2], t[1]))
        assert abs((chi + 90) % 180 - 90) < 2.0
        assert abs(src["circular_fraction"] - t[3] / t[0]) < 0.05 * max(abs(t[3] / t[0]), 0.01)


def test_the_condition_number_flags_where_the_response_says_polarisation_is_not_measured(cleaned):
    """The stated cond(A) is large exactly where the maps hold almost nothing of a source's polarisation:
    at the test declinations, cond(A) > COND_MAX where the response's smallest ratio is below 0.05 (and the
    components where it is large are I alone), and below it where the ratios are >= 0.1."""
    observe, _, result, _ = cleaned
    decs = np.deg2rad([-30.0, -10.0, 20.0, 45.0, 70.0])
    resp = polarisation_response(observe, decs)
    cond = np.linalg.cond(matrices_at(result["table"], radec_to_vec(np.zeros(5), decs)))  # the CLEAN's table
    worst = np.abs([resp[f"ratio_{x}"] for x in "quv"]).min(axis=0)
    print("\ncond", np.round(cond, 1), "smallest response ratio", np.round(worst, 3))
    assert not resp["measured"]
    assert np.all((cond > COND_MAX) == (worst < 0.05)) and np.all(cond[worst >= 0.1] < COND_MAX)
    low = np.linalg.cond(matrices_at(result["table"], result["vec"])) > COND_MAX
    assert low.any() and np.all(result["stokes"][low, 1:] == 0) and np.all(result["stokes"][~low, 1:] != 0)


def test_closing_the_sources_gives_the_restored_maps_the_stated_stokes_vectors(lmax32, cleaned):
    """The restored maps (residual + components, :func:`mmflow.imaging.clean.restore_map`) at each measured
    source's pixel: after :func:`close_sources` (each source's last step taken into the CLEAN: A(r)^-1 of the
    residual there, its image subtracted) the linear and circular fractions are within 5 % of the truth and the
    angles within 2 deg; the sources stated afterwards are the ones stated before (within 0.5 % of I). Before,
    the residual at a source holds the prior's shrunken part of what the components left."""
    import copy

    import healpy

    _, _, vecs, _ = lmax32
    observe, _, result, sources = cleaned
    closed = copy.deepcopy(result)
    assert close_sources(observe, closed) == sources  # the sources stated, from the same grouping
    nside = 64

    def restored(res):
        maps = stokes_maps(res["residual"], nside, 32)
        return np.array([restore_map(maps[x], res["vec"], res["stokes"][:, x], res["table"]) for x in range(4)])

    before, after = restored(result), restored(closed)
    truth = np.c_[FLUX, FLUX[:, None] * SOURCES[:, 2:]]
    for k, (vec, t) in enumerate(zip(vecs, truth)):
        src = _nearest(sources, vec)
        again = _nearest(stokes_sources(closed, 32), vec)
        assert again["measured"] == src["measured"]
        if not src["measured"]:
            continue
        assert np.abs(np.subtract(again["stokes_jy"], src["stokes_jy"])).max() < 0.005 * src["stokes_jy"][0]
        pix = healpy.vec2pix(nside, *vec)
        lin_true = np.hypot(*t[1:3]) / t[0]
        if lin_true == 0 and t[3] == 0:
            assert np.abs(after[1:, pix]).max() < 0.005 * after[0, pix]
            continue
        was, now = (np.hypot(*m[1:3, pix]) / m[0, pix] / lin_true for m in (before, after))
        chi = 0.5 * np.rad2deg(np.arctan2(after[2, pix], after[1, pix]) - np.arctan2(t[2], t[1]))
        v_was, v_now = (m[3, pix] / m[0, pix] - t[3] / t[0] for m in (before, after))  # V / I's error
        print(f"source {k}: restored linear fraction / truth {was:.4f} -> {now:.4f}, V / I error {v_was:.4f} -> "
              f"{v_now:.4f}, angle error {chi:.2f} deg")
        assert abs(now - 1) < 0.05 and abs((chi + 90) % 180 - 90) < 2.0
        assert abs(v_now) < 0.05 * max(abs(t[3] / t[0]), 0.1)
