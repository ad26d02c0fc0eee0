"""The corruption simulator injects what the paper describes, seeded and switchable."""
import numpy as np
import pytest

from mmflow.calibrate.coherency import source_coherencies, source_vector_date
from mmflow.simulate.corrupt import (ARCMIN, antenna_gains, corrupt, crosstalk_pattern, dd_visibilities,
                                     direction_dependent_gains, flag_weights, gain_products, ionospheric_offsets,
                                     near_field_rfi, rank1_visibilities, sawtooth_db, scintillation)
from mmflow.simulate.scene import source_points_date
from mmflow.simulate.visibilities import simulate_drift_scan
from mmflow.sky.sources import CATALOG

EPOCH = 2457700.5


def test_sawtooth_is_a_tenth_of_a_db_with_a_15_to_17_minute_period(rng):
    t = np.arange(0, 6 * 3600, 13.0)
    db = sawtooth_db(t, rng)
    assert np.ptp(db) == pytest.approx(0.1, abs=0.005)
    drops = np.flatnonzero(np.diff(db) < -0.05)  # the sawtooth resets
    periods = np.diff(t[drops]) / 60
    assert periods.min() > 14.7 and periods.max() < 17.3
    assert np.ptp(periods) > 0.5  # the period wanders
    g, power = antenna_gains(4, 2, t, np.random.default_rng(3), bandpass=False, drift=False)
    np.testing.assert_allclose(np.abs(g) ** 2, power)
    g2, _ = antenna_gains(4, 2, t, np.random.default_rng(3), bandpass=False, drift=False)
    np.testing.assert_array_equal(g, g2)  # seeded
    off, _ = antenna_gains(4, 2, t, rng, bandpass=False, drift=False, sawtooth=False)
    assert (off == 1).all()  # switchable


def test_ionospheric_offsets_reach_20_arcmin_at_36_MHz_and_scale_as_nu_minus_2(rng):
    t = np.arange(0, 3600, 13.0)
    lo = ionospheric_offsets(3, t, 36.5e6, np.random.default_rng(1))
    hi = ionospheric_offsets(3, t, 73e6, np.random.default_rng(1))
    assert np.linalg.norm(lo, axis=-1).max() == pytest.approx(20 * ARCMIN)
    np.testing.assert_allclose(hi, lo / 4)
    # varying on ~10 minutes: little change between 13 s integrations, a lot over 10 min
    step = np.linalg.norm(np.diff(lo, axis=1), axis=-1).mean()
    ten = np.linalg.norm(lo[:, 46:] - lo[:, :-46], axis=-1).mean()
    assert step < 0.15 * ten
    s = scintillation(2, 2000, 36.5e6, rng)
    jump = np.abs(np.diff(s, axis=1)) / s[:, :-1]
    # "not unusual for Cyg A to have flux variations of 50 % between adjacent integrations"
    assert 0.03 < np.mean(jump > 0.5) < 0.2 and s.mean() == pytest.approx(1, abs=0.03)


def test_dd_gains_move_a_source_by_its_refractive_offset(small_telescope):
    tel = small_telescope
    freq = tel.freqs_hz[0]
    pairs = tel.antenna_pairs()
    src = CATALOG["Cyg A"]
    lsts = np.deg2rad(np.array([280.0, 300.0, 320.0]))
    off = np.deg2rad(np.array([[[2.0, -1.0], [0.5, 1.5], [-1.0, 0.0]]]))  # degrees: visible on 30 m
    coh = source_coherencies(tel, freq, lsts, [src], EPOCH, pairs)
    h = direction_dependent_gains(tel, freq, lsts, source_vector_date(src, EPOCH)[None], off)
    moved = dd_visibilities(coh, h, pairs)
    for t in range(3):
        direct = simulate_drift_scan(
            tel, freq, lsts[t : t + 1], source_points_date(src, freq, EPOCH, off[0, t]), pairs
        )[0]
        # the phase gradient moves the fringe (to first order in the offset); the beam stays
        # the one at the catalogue position, so the amplitude ratio is one number per time
        ratio = moved[t] / direct
        assert np.abs(np.angle(ratio)).max() < 0.02
        assert np.ptp(np.abs(ratio)) < 1e-9
        assert np.abs(np.angle(moved[t] / coh[0, t])).max() > 0.1


def test_terrestrial_components_are_rank_one_and_do_not_move(small_telescope, rng):
    tel = small_telescope
    pairs = tel.antenna_pairs()
    enu = tel.layout.enu
    e, amp = near_field_rfi(enu, tel.freqs_hz[0], 50, rng, distance_m=10e3)
    # spherical wavefront: phases follow the distance to the emitter, not a plane wave
    d = np.linalg.norm(enu - np.array([-10e3, 0, 0]), axis=1)
    np.testing.assert_allclose(np.angle(e * np.exp(-2j * np.pi * d * tel.freqs_hz[0] / 299792458.0)), 0, atol=1e-9)
    assert amp.min() >= 0 and amp.std() > 0.1 * amp.mean()
    c = crosstalk_pattern(tel.n_ant, rng)
    v = rank1_visibilities(c, np.ones(3), pairs)
    np.testing.assert_array_equal(v[0], v[2])
    full = np.zeros((tel.n_ant, tel.n_ant), complex)
    full[pairs[:, 0], pairs[:, 1]] = v[0]
    full[pairs[:, 1], pairs[:, 0]] = np.conj(v[0])
    s = np.linalg.svd(full, compute_uv=False)
    assert s[1] < 1e-10 * s[0]


def test_corrupt_applies_gains_terrestrial_flags_and_radiometer_noise(small_telescope, rng):
    tel = small_telescope
    pairs = tel.antenna_pairs()
    T = 400
    sky = np.ones((T, len(pairs), 2), complex) * 100.0
    sky[:, pairs[:, 0] == pairs[:, 1]] = 1e4
    g, _ = antenna_gains(tel.n_ant, 2, np.arange(T) * 13.0, rng)
    w, bad_ant, bad_t = flag_weights(T, pairs, 2, rng, n_bad_antennas=1, bad_integration_fraction=0.05)
    c = crosstalk_pattern(tel.n_ant, rng, 3.0)
    out, truth = corrupt(sky, pairs, rng, gains=g, terrestrial=[(c, np.ones(T))],
                         noise={"bandwidth_hz": 24e3, "integration_s": 13.0}, weights=w)
    assert (out[w == 0] == 0).all() and len(bad_t) > 0 and len(bad_ant) == 1
    clean = (sky + rank1_visibilities(c, np.ones(T), pairs)[..., None]) * gain_products(g, pairs)
    resid = (out - clean)[w > 0]
    sigma = truth.noise_sigma[w > 0]
    # radiometer equation: sigma = sqrt(V_ii V_jj / (dnu tau)) per complex visibility
    assert np.mean(np.abs(resid) ** 2 / sigma**2) == pytest.approx(1.0, rel=0.05)


@pytest.mark.parametrize("fmt", ["uvh5", "ms"])
def test_corrupted_data_written_through_pyuvdata_read_back(small_telescope, rng, tmp_path, fmt):
    from pyuvdata import UVData

    from mmflow.simulate.corrupt import to_uvdata

    if fmt == "ms":
        pytest.importorskip("casacore")  # the optional 'ms' extra

    tel = small_telescope
    pairs = tel.antenna_pairs()
    T = 3
    vis = rng.normal(size=(T, len(pairs), 2)) + 1j * rng.normal(size=(T, len(pairs), 2))
    vis[:, pairs[:, 0] == pairs[:, 1]] = np.abs(vis[:, pairs[:, 0] == pairs[:, 1]])
    w = np.ones(vis.shape)
    w[1, 3] = 0
    jd = 2457700.5 + np.arange(T) * 13.0 / 86400
    uv = to_uvdata(vis, w, pairs, tel, jd, tel.freqs_hz[0])
    path = tmp_path / f"c.{fmt}"
    if fmt == "uvh5":
        uv.write_uvh5(str(path))
    else:
        uv.write_ms(str(path), force_phase=True)  # an MS must carry a phase centre
    back = UVData.from_file(str(path), **({"ignore_single_chan": False} if fmt == "ms" else {}))
    if fmt == "ms":
        back.unproject_phase()  # back to the drift scan
    for b, (i, j) in enumerate(pairs[:10]):
        d = back.get_data(int(i), int(j), "xx")
        np.testing.assert_allclose(d[:, 0], vis[:, b, 0], rtol=1e-6)
    assert back.get_flags(int(pairs[3, 0]), int(pairs[3, 1]), "yy")[1, 0]
    # baselines point from ant_1 to ant_2 (x_j - x_i), as mmflow's convention
    uvw = back.uvw_array[back.antpair2ind(int(pairs[5, 0]), int(pairs[5, 1]))][0]
    b_enu = tel.baselines_enu(pairs[5:6])[0]
    assert np.linalg.norm(uvw) == pytest.approx(np.linalg.norm(b_enu), rel=1e-3)
    assert np.abs(uvw[2] - b_enu[2]) < 0.01 * np.linalg.norm(b_enu)  # zenith w = up component
