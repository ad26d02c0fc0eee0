"""Polarisation leakage (D-terms) of a simulated array, imaged without polarisation calibration
(issue 22: "the leakage terms of a simulated array must not break the imaging of I").

The scene of tests/polarised_scene.py (20 antennas, 300 integrations, lmax 32); each antenna's
feeds leak ``D_i = [[1, d_ix], [-d_iy, 1]]`` (:func:`mmflow.simulate.polarised.apply_leakage`)
with ``|d|`` uniform in 1-5 % and random phases (fixed seed), typical of a dipole array. Data
with and without D-terms are imaged through the same operators (the full-Stokes solve, and the
Stokes-I engine on ``(xx + yy) / 2``), so a map difference is the D-terms' effect alone.

First order in d, for an unpolarised source seen at the zenith (``xx = yy = I``,
``xy = yx = 0``): ``xy' = (d_ix - conj(d_jy)) I``, ``yx' = (conj(d_jx) - d_iy) I``, i.e. in the
feed frame ``U = Re <d_x - d_y> I``, ``V = +Im <d_x + d_y> I`` (from ``xy = U + iV``, ``yx = U - iV`` at
the zenith, the IAU sign under mmflow's fringe, docs/conventions.md; ``-Im`` before issue 39,
which had ``xy = U - iV``; ``<>``: the array mean; the
antenna-to-antenna scatter is not a sky and is imaged like noise) and ``Q = 0``. V does not
depend on the frame: the V leak of the array-mean D-terms is that V imaged through the same
operator.
"""
import healpy as hp
import numpy as np
import pytest

from mmflow.errors import InputError
from mmflow.imaging.polarised import (accumulate_polarised_normal, expected_alm, point_source_stokes_alm,
                                      solve_polarised, stokes_maps)
from mmflow.imaging.solvers import solve_alm
from mmflow.mmode.engine import accumulate_normal_equations
from mmflow.mmode.polarised import make_polarised_grid
from mmflow.mmode.transfer import baselines_in_wavelengths, fringe_bandlimit
from mmflow.mmode.transform import mmode_transform
from mmflow.simulate.polarised import CORRELATIONS, PolarisedPoints, apply_leakage, simulate_polarised_drift_scan
from mmflow.sky.diffuse import alm_to_map
from mmflow.telescope import Telescope
from mmflow.telescope.jones import ShortDipoleJones
from tests.polarised_scene import (EPS_I, EPS_POL, FREQ, LMAX, N_LST, NO_FILTER, NSIDE, POL_FRAC, POL_I,
                                   POL_RADEC, UNPOL_I, UNPOL_RADEC, peak_near, radec_vectors, scene_layout)

SEED, THETA = 22, 0.03  # D-term draw; a common feed rotation of 0.03 rad
EPS_FIRM = 1e-4  # a firmer eps_I (eps_pol = EPS_POL / EPS_I times it) beside the scene's 1e-6


def test_apply_leakage_is_the_jones_product_per_baseline():
    """``V'_ij = D_i V_ij D_j^H`` per baseline (autocorrelations and both orders of a pair), in any
    order of the correlation axis; a common small rotation (``d_x = d_y = theta``) scales
    ``xx + yy`` by ``1 + theta^2`` exactly; the simulator's ``dterms`` is the same corruption."""
    rng = np.random.default_rng(0)
    n_ant, n_t = 5, 3
    pairs = np.array([[0, 0], [0, 1], [1, 0], [1, 3], [2, 4], [4, 4]])
    vis = rng.normal(size=(n_t, 4, len(pairs))) + 1j * rng.normal(size=(n_t, 4, len(pairs)))
    d = 0.05 * (rng.normal(size=(n_ant, 2)) + 1j * rng.normal(size=(n_ant, 2)))
    got = apply_leakage(vis, pairs, d)
    for t in range(n_t):
        for k, (i, j) in enumerate(pairs):
            v = np.array([[vis[t, 0, k], vis[t, 2, k]], [vis[t, 3, k], vis[t, 1, k]]])  # [[xx, xy], [yx, yy]]
            di, dj = (np.array([[1, d[a, 0]], [-d[a, 1], 1]]) for a in (i, j))
            want = di @ v @ dj.conj().T
            np.testing.assert_allclose(got[t, :, k], [want[0, 0], want[1, 1], want[0, 1], want[1, 0]], atol=1e-14)
    order = [3, 0, 2, 1]  # yx, xx, xy, yy
    np.testing.assert_allclose(apply_leakage(vis[:, order], pairs, d, [CORRELATIONS[c] for c in order]),
                               got[:, order], atol=1e-14)
    rot = apply_leakage(vis, pairs, np.full((n_ant, 2), THETA))
    np.testing.assert_allclose(rot[:, 0] + rot[:, 1], (1 + THETA ** 2) * (vis[:, 0] + vis[:, 1]), atol=1e-13)
    with pytest.raises(InputError):
        apply_leakage(vis[:, :2], pairs, d, ("xx", "yy"))
    jones = ShortDipoleJones(horizon_taper=3.0)
    tel = Telescope(scene_layout(6, 6.0), jones.power_beam(), [FREQ])
    sky = PolarisedPoints(radec_vectors(POL_RADEC), np.c_[POL_I, POL_I[:, None] * POL_FRAC])
    lst = np.linspace(0, 2 * np.pi, 7)
    d6 = 0.03 * np.exp(2j * np.pi * rng.uniform(size=(6, 2)))
    full = apply_leakage(simulate_polarised_drift_scan(tel, jones, FREQ, lst, sky), tel.antenna_pairs(), d6)
    np.testing.assert_allclose(simulate_polarised_drift_scan(tel, jones, FREQ, lst, sky, correlations=("yy", "xy"),
                                                             dterms=d6), full[:, [1, 2]], atol=1e-12)


@pytest.fixture(scope="module")
def setup():
    jones = ShortDipoleJones(horizon_taper=3.0)
    tel = Telescope(scene_layout(), jones.power_beam(), [FREQ])
    pairs, n_ant = tel.antenna_pairs(), len(tel.layout.enu)
    rng = np.random.default_rng(SEED)
    d = rng.uniform(0.01, 0.05, (n_ant, 2)) * np.exp(2j * np.pi * rng.uniform(size=(n_ant, 2)))
    dterms = {"none": None, "random": d, "mean": np.broadcast_to(d.mean(axis=0), d.shape),
              "rotation": np.full((n_ant, 2), THETA + 0j)}
    z = np.zeros(4)
    skies = {"pol": PolarisedPoints(radec_vectors(POL_RADEC), np.c_[POL_I, POL_I[:, None] * POL_FRAC]),
             "unpol": PolarisedPoints(radec_vectors(UNPOL_RADEC), np.c_[UNPOL_I, z, z, z])}
    lst = 2 * np.pi * np.arange(N_LST) / N_LST
    vis = {s: simulate_polarised_drift_scan(tel, jones, FREQ, lst, sky) for s, sky in skies.items()}
    keys = [(s, k) for s in skies for k in dterms]
    mm = np.stack([mmode_transform(vis[s] if dterms[k] is None else apply_leakage(vis[s], pairs, dterms[k]), LMAX)
                   for s, k in keys])  # (vec, m, 2, corr, bl)
    b = baselines_in_wavelengths(tel, pairs, FREQ)
    grid = make_polarised_grid(tel.lat_rad, jones, FREQ, LMAX, fringe_bandlimit(np.linalg.norm(b, axis=1),
                                                                                  jones.lmax_hint))
    normal = accumulate_polarised_normal(grid, b, mm)
    scale = max(np.abs(np.diag(g)).max() for g in normal.gram)
    acc = accumulate_normal_equations(tel, FREQ, 0.5 * (mm[:, :, :, 0] + mm[:, :, :, 1]), LMAX,
                                      per_baseline_lmax=False)
    scale_i = max(np.abs(np.diag(acc.full_gram(m))).max() for m in range(LMAX + 1))
    full, scalar = {}, {}
    for eps_i in (EPS_I, EPS_FIRM):
        eps = (eps_i * scale, eps_i * EPS_POL / EPS_I * scale)
        full[eps_i] = dict(zip(keys, (stokes_maps(a, NSIDE, LMAX) for a in solve_polarised(normal, eps))))
        scalar[eps_i] = {key: alm_to_map(solve_alm(acc, eps_i * scale_i, filters=NO_FILTER, split=n), NSIDE, LMAX)
                         for n, key in enumerate(keys)}
    return dict(tel=tel, pairs=pairs, d=d, skies=skies, vis=vis, normal=normal, scale=scale, full=full,
                scalar=scalar)


def test_stokes_i_peaks_survive_uncalibrated_dterms(setup):
    """I peaks with D-terms / without, both imaging paths, all eight sources: within 3 % at the
    scene's eps_I 1e-6 (measured <= 2.3 %), within 1 % at eps_I 1e-4 (measured <= 0.9 %), peaks
    moved < 0.05 FWHM; the array-mean D-terms alone change unpolarised sources' peaks < 0.1 %.

    The change is first order in d and comes mostly from the antenna-to-antenna scatter of the
    D-terms: per baseline it is data no sky fits, which a weakly regularised solve (lmax beyond
    the array's resolution) images like noise; the array-mean part changes ``xx + yy`` only
    through the cross hands (polarised sources: ``<d> (U, V)``, up to 0.8 %)."""
    worst = {}
    for eps_i, limit in ((EPS_I, 0.03), (EPS_FIRM, 0.01)):
        for path in ("full", "scalar"):
            maps = setup[path][eps_i]
            i_map = (lambda key: maps[key][0]) if path == "full" else (lambda key: maps[key])  # noqa: E731
            for s, sky in setup["skies"].items():
                for variant in ("random", "mean"):
                    for k, vec in enumerate(sky.vectors):
                        ref, got = peak_near(i_map((s, "none")), vec), peak_near(i_map((s, variant)), vec)
                        rel = got["peak"] / ref["peak"] - 1
                        moved = np.arccos(min(1.0, got["vec"] @ ref["vec"])) / ref["fwhm_rad"]
                        print(f"eps_I {eps_i:.0e} {path:6s} {s:5s} source {k} D {variant:6s}: "
                              f"I peak {rel:+.4%}, moved {moved:.4f} FWHM")
                        assert abs(rel) < limit, (eps_i, path, s, variant, k, rel)
                        assert moved < 0.05, (eps_i, path, s, variant, k, moved)
                        if s == "unpol" and variant == "mean":
                            assert abs(rel) < 1e-3, (eps_i, path, k, rel)
                        worst[eps_i, variant] = max(worst.get((eps_i, variant), 0.0), abs(rel))
    print("largest |I peak change|:", {f"{e:.0e} {v}": f"{x:.3%}" for (e, v), x in worst.items()})


def test_dterms_leak_i_into_q_u_v_at_the_d_level(setup):
    """Unpolarised sky, map with D-terms minus map without (scene eps): Q, U, V within one FWHM
    of each source are a few tenths of a percent to ~2.5 % of its I peak, < 3 max|d| (measured
    max|d| ~ 5 %). V: the array-mean D-terms give ``V = +Im <d_x + d_y> I`` imaged through the
    same operator to 5 % (measured <= 2.2 %) at every source (2-47 deg from the zenith); the
    random D-terms give that sign and 0.5-3 times it (scatter on top; measured 1.3-1.8)."""
    d, sky = setup["d"], setup["skies"]["unpol"]
    maps = setup["full"][EPS_I]
    v_pred = np.mean(d[:, 0] + d[:, 1]).imag
    eps = (EPS_I * setup["scale"], EPS_POL * setup["scale"])
    stokes = np.c_[np.zeros((len(sky.vectors), 3)), v_pred * sky.stokes_jy[:, 0]]
    v_imaged = stokes_maps(expected_alm(setup["normal"], point_source_stokes_alm(sky.vectors, stokes, LMAX),
                                        eps)[0], NSIDE, LMAX)[3]
    print(f"max|d| {np.abs(d).max():.3f}, <d_x> {np.mean(d[:, 0]):.4f}, <d_y> {np.mean(d[:, 1]):.4f}: "
          f"predicted V / I {v_pred:+.4f}, feed-frame U / I {np.mean(d[:, 0] - d[:, 1]).real:+.4f}")
    for k, vec in enumerate(sky.vectors):
        clean = maps["unpol", "none"]
        pk = peak_near(clean[0], vec)
        disc, pix = hp.query_disc(NSIDE, vec, pk["fwhm_rad"]), hp.vec2pix(NSIDE, *vec)
        leak = {}
        for variant in ("random", "mean"):
            diff = maps["unpol", variant] - clean
            leak[variant] = np.abs(diff[1:, disc]).max(axis=1) / pk["peak"]
            ratio = diff[3, pix] / v_imaged[pix]
            print(f"source {k} D {variant:6s}: max |Q|, |U|, |V| " + ", ".join(f"{x:.3%}" for x in leak[variant])
                  + f" of I; P at source {np.hypot(*diff[1:3, pix]) / pk['peak']:.3%}; V / prediction {ratio:.3f}")
            if variant == "mean":
                assert ratio == pytest.approx(1, abs=0.05), (k, ratio)
            else:
                assert 0.5 < ratio < 3, (k, ratio)
        assert leak["random"].max() < 3 * np.abs(d).max(), (k, leak)


def test_scalar_stokes_i_path_sees_dterms_only_through_the_cross_hands(setup):
    """``(xx' + yy') / 2 - (xx + yy) / 2 = [(conj(d_jx) - d_iy) xy + (d_ix - conj(d_jy)) yx] / 2
    + [d_ix conj(d_jx) yy + d_iy conj(d_jy) xx] / 2``: no first-order term without cross hands
    (unpolarised source at the zenith) nor for a common feed rotation (``d_x = d_y`` real), whose
    Stokes-I map is exactly ``1 + theta^2`` times the map without it. Here the unpolarised sky's
    cross hands (the dipoles' non-orthogonal projection off the zenith) are <= 6.5 % of ``V_I``,
    the polarised sky's (U, V) <= 40 %."""
    d, pairs = setup["d"], setup["pairs"]
    i, j = pairs[:, 0], pairs[:, 1]
    for s, vis in setup["vis"].items():
        xx, yy, xy, yx = (vis[:, c] for c in range(4))
        got = apply_leakage(vis, pairs, d)
        first = 0.5 * ((d[j, 0].conj() - d[i, 1]) * xy + (d[i, 0] - d[j, 1].conj()) * yx)
        second = 0.5 * (d[i, 0] * d[j, 0].conj() * yy + d[i, 1] * d[j, 1].conj() * xx)
        delta = 0.5 * (got[:, 0] + got[:, 1]) - 0.5 * (xx + yy)
        np.testing.assert_allclose(delta, first + second, atol=1e-12 * np.abs(vis).max())
        v_i = np.abs(0.5 * (xx + yy)).max()
        cross = np.abs(vis[:, 2:]).max() / v_i
        print(f"{s}: max |xy|, |yx| / max V_I {cross:.3f}; max |first-order| {np.abs(first).max() / v_i:.2e}, "
              f"|second-order| {np.abs(second).max() / v_i:.2e} of max V_I")
        assert cross < (0.065 if s == "unpol" else 0.4)
        for eps_i in (EPS_I, EPS_FIRM):
            maps = setup["scalar"][eps_i]
            np.testing.assert_allclose(maps[s, "rotation"], (1 + THETA ** 2) * maps[s, "none"],
                                       atol=1e-9 * np.abs(maps[s, "none"]).max())


def test_simulated_chunk_noise_follows_the_radiometer_equation_of_each_feed_pair():
    """The simulate stage's full-Stokes chunk: the noise on each correlation pq of baseline (i, j) has
    variance V_ii^pp V_jj^qq / (dnu tau) (complex on cross correlations, real on the parallel hands'
    autocorrelations), and without noise the parallel and cross hands are the direct sums'."""
    from mmflow.simulate.polarised import PolarisedPoints, simulate_polarised_drift_scan
    from mmflow.simulate.scene import simulate_polarised_chunk
    from mmflow.telescope import Telescope
    from mmflow.telescope.jones import ShortDipoleJones
    from tests.stokes_helpers import compact_layout

    jones = ShortDipoleJones(3.0)
    tel = Telescope(compact_layout(4), jones.power_beam(), [40e6], include_autos=True)
    tel.channel_width_hz = 24e3
    sky = [PolarisedPoints(np.array([[0.3, 0.2, 0.93]]) / np.linalg.norm([0.3, 0.2, 0.93]),
                           np.array([[1e5, 3e4, -2e4, 1e4]]))]
    lsts = np.full(4000, 0.4)  # one sky, many noise draws
    par, cross = simulate_polarised_chunk(tel, jones, lsts, sky)
    exact = simulate_polarised_drift_scan(tel, jones, 40e6, lsts[:1], sky[0], tel.antenna_pairs())[0]  # (corr, bl)
    np.testing.assert_allclose(np.concatenate([par[0, :, 0], cross[0, :, 0]], axis=-1), exact.T, rtol=1e-6, atol=1e-3)
    npar, ncross = simulate_polarised_chunk(tel, jones, lsts, sky, np.random.default_rng(0), integration_s=13.0)
    noise = np.concatenate([npar - par, ncross - cross], axis=-1)[:, :, 0]  # (time, bl, corr)
    pairs = tel.antenna_pairs()
    auto = {int(i): exact[:2, b].real for b, (i, j) in enumerate(pairs) if i == j}  # xx, yy autos per antenna
    for b, (i, j) in enumerate(pairs):
        for c, (p, q) in enumerate(("xx", "yy", "xy", "yx")):
            var = auto[int(i)]["xy".index(p)] * auto[int(j)]["xy".index(q)] / (24e3 * 13.0)
            n = noise[:, b, c]
            assert abs(np.mean(np.abs(n) ** 2) / var - 1) < 0.1, (b, c)
            assert (np.abs(n.imag).max() == 0) == (i == j and p == q), (b, c)
        if i == j:  # an autocorrelation's yx is conj(xy), noise included
            np.testing.assert_array_equal(ncross[:, b, 0, 1], np.conj(ncross[:, b, 0, 0]))
