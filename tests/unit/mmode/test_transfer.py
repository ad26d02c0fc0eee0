"""Transfer coefficients against brute-force quadrature, symmetries, per-baseline lmax."""
import ducc0
import numpy as np
from scipy.special import sph_harm_y

from mmflow.conventions import enu_to_equatorial_matrix, unit_vectors
from mmflow.mmode.transfer import (baselines_in_wavelengths, fringe_bandlimit, make_grid, transfer_blocks)
from mmflow.telescope.beams import GaussianBeam, SinElevationBeam

LAT = np.deg2rad(37.24)


_GRIDS = {}


def _grid(nt, nph):
    """Gauss-Legendre colatitudes and weights, and longitudes offset from any ring grid."""
    if (nt, nph) not in _GRIDS:
        th = ducc0.misc.GL_thetas(nt)
        ph = 2 * np.pi * (np.arange(nph) + 0.37) / nph
        _GRIDS[nt, nph] = th, ducc0.misc.GL_weights(nt, nph), ph, unit_vectors(th[:, None], ph[None, :])
    return _GRIDS[nt, nph]


def brute_force(beam, b, l, m, freq=50e6, nt=320, nph=640):
    """int A exp(2 pi i b.r) Y_lm dOmega on an independent, offset, much finer grid
    (``Y_lm(theta, phi) = Y_lm(theta, 0) e^{i m phi}``, scipy's Y_lm on the colatitudes)."""
    th, w, ph, vec = _grid(nt, nph)
    a = beam.power_enu(vec @ enu_to_equatorial_matrix(LAT), freq)
    f = a * np.exp(2j * np.pi * (vec @ b))
    y = sph_harm_y(l, m, th, 0.0)[:, None] * np.exp(1j * m * ph)[None, :]
    return np.sum(w[:, None] * f * y)


def test_fast_coefficients_match_brute_force_float64():
    beam = GaussianBeam(30)
    rng = np.random.default_rng(0)
    b = np.array([[3.0, -2.0, 0.5], [0.0, 0.0, 0.0], [-5.0, 1.0, 0.2]])
    lmax = 40
    grid = make_grid(LAT, beam, 50e6, lmax, fringe_bandlimit(np.linalg.norm(b, axis=1), beam.lmax_hint))
    blocks = transfer_blocks(grid, b, dtype=np.float64)
    peak = max(np.abs(blk).max() for blk in blocks)
    for _ in range(12):
        m = int(rng.integers(0, lmax + 1))
        l = int(rng.integers(m, lmax + 1))
        for i in range(3):
            ref = brute_force(beam, b[i], l, m)
            assert abs(blocks[m][i, l - m] - ref) <= 1e-6 * max(abs(ref), 1e-3 * peak)
            if m > 0:  # the -m row of b is the +m row of -b
                assert abs(blocks[m][3 + i, l - m] - brute_force(beam, -b[i], l, m)) <= 1e-6 * peak


def test_minus_m_row_equals_plus_m_row_of_reversed_baseline(small_telescope):
    tel = small_telescope
    pairs = tel.antenna_pairs()[:6]
    b = baselines_in_wavelengths(tel, pairs, 40e6)
    lmax = 30
    grid = make_grid(tel.lat_rad, tel.beam, 40e6, lmax, fringe_bandlimit(np.linalg.norm(b, axis=1), 24))
    fwd = transfer_blocks(grid, b)
    rev = transfer_blocks(grid, -b)
    for m in range(1, lmax + 1):
        np.testing.assert_allclose(fwd[m][6:], rev[m][:6], atol=1e-13)


def test_float32_close_to_float64(small_telescope):
    tel = small_telescope
    b = baselines_in_wavelengths(tel, tel.antenna_pairs()[:10], 40e6)
    grid = make_grid(tel.lat_rad, tel.beam, 40e6, 30, fringe_bandlimit(np.linalg.norm(b, axis=1), 24))
    b64 = transfer_blocks(grid, b, dtype=np.float64)
    b32 = transfer_blocks(grid, b, dtype=np.float32)
    assert b32[3].dtype == np.complex64
    peak = max(np.abs(x).max() for x in b64)
    assert max(np.abs(x - y).max() for x, y in zip(b32, b64)) < 1e-5 * peak


def test_per_baseline_lmax_truncation_is_small():
    """Beyond lmax_b = 1.1 * 2 pi |b| / lambda + beam hint the coefficients are negligible."""
    beam = SinElevationBeam(2.0)
    b = np.array([[6.0, 2.0, 0.1]])
    lmax = 90
    grid = make_grid(LAT, beam, 50e6, lmax, fringe_bandlimit([np.linalg.norm(b)], beam.lmax_hint))
    full = transfer_blocks(grid, b)
    lmax_b = int(np.ceil(1.1 * 2 * np.pi * np.linalg.norm(b))) + beam.lmax_hint
    assert lmax_b < lmax
    cut = transfer_blocks(grid, b, lmax_b=np.array([lmax_b]))
    total = np.sqrt(sum(np.sum(np.abs(x) ** 2) for x in full))
    lost = np.sqrt(sum(np.sum(np.abs(x - y) ** 2) for x, y in zip(full, cut)))
    assert lost / total < 1e-3


def test_celestial_pole_source_excites_only_m0(small_telescope):
    """A point source at the pole does not move: its m-modes vanish for m != 0."""
    from mmflow.mmode.transform import mmode_transform, sidereal_bins
    from mmflow.simulate.visibilities import SkyPoints, simulate_drift_scan

    tel = small_telescope
    n = 64
    lst = 2 * np.pi * np.arange(n) / n
    vis = simulate_drift_scan(tel, 40e6, lst, SkyPoints(np.array([[0.0, 0.0, 1.0]]), np.array([100.0])))
    mm = mmode_transform(sidereal_bins(lst, vis, n_bins=n)[0], 20)
    assert np.abs(mm[0, 0]).max() > 0.01  # 100 Jy seen 53 deg from zenith by a 30 deg beam
    assert np.abs(mm[1:]).max() < 1e-9 * np.abs(mm[0, 0]).max()


def test_uniform_sky_autocorrelation_is_temperature_times_beam_solid_angle(small_telescope):
    """V_ii of a uniform T sky = (2 k T nu^2 / c^2) * Omega_beam, in Jy; here through B (l = 0)."""
    from mmflow.sky.units import jy_per_sr_per_kelvin

    tel = small_telescope
    freq, temp = 40e6, 5000.0
    grid = make_grid(tel.lat_rad, tel.beam, freq, 10, fringe_bandlimit([0.0], 24))
    b00 = transfer_blocks(grid, np.zeros((1, 3)), mmax=0)[0][0, 0]
    a00 = temp * jy_per_sr_per_kelvin(freq) * np.sqrt(4 * np.pi)  # uniform I: a_00 = I sqrt(4 pi)
    # beam solid angle by direct integration in the local frame: 2 pi int A(za) sin(za) dza
    za = np.linspace(0, np.pi / 2, 20001)
    omega = 2 * np.pi * np.trapezoid(tel.beam.power(np.zeros_like(za), za, freq) * np.sin(za), za)
    expected = temp * jy_per_sr_per_kelvin(freq) * omega
    assert abs(b00 * a00 - expected) < 1e-6 * expected


def test_compiled_fringe_kernel_matches_numpy():
    """The polynomial sincos and the folded north/south fringes against numpy's sin/cos/exp."""
    from mmflow.mmode.fringe_kernels import fringe_folds, sincos_turns

    t = np.random.default_rng(0).uniform(-400, 400, 20000)  # turns: baselines of hundreds of wavelengths
    for dtype, tol in ((np.float32, 3e-7), (np.float64, 1e-12)):
        s, c = sincos_turns(t, dtype)
        assert np.abs(s - np.sin(2 * np.pi * t)).max() < tol
        assert np.abs(c - np.cos(2 * np.pi * t)).max() < tol
    rng = np.random.default_rng(1)
    vec = unit_vectors(rng.uniform(0, np.pi / 2, 3)[:, None], rng.uniform(0, 2 * np.pi, (3, 50)))  # 3 rings
    b = rng.normal(size=(7, 3)) * 60
    beam_n, beam_s = rng.uniform(size=(2, 3, 50))
    beam_n[0, :10] = beam_s[0, :10] = 0  # both rings below the horizon
    rot = np.exp(-4j * np.pi * vec[:, :1, 2] * b[None, :, 2])
    north = beam_n[..., None] * np.exp(2j * np.pi * vec @ b.T)
    mirror = vec * [1, 1, -1]
    south = beam_s[..., None] * np.exp(2j * np.pi * mirror @ b.T)
    for cdtype, tol in ((np.complex64, 3e-6), (np.complex128, 1e-11)):
        out_s, out_d = np.full((2, 3, 50, 7), np.nan, cdtype)
        fringe_folds(vec, b, beam_n, beam_s, rot, out_s, out_d)
        np.testing.assert_allclose(out_s, north + south, atol=tol)
        np.testing.assert_allclose(out_d, north - south, atol=tol)


def test_compiled_kernels_load_from_numba_cache_in_a_new_process(tmp_path):
    """Every worker process would otherwise compile the Legendre recurrence, the spin-2 tables and the
    fringe kernels again (1-2 s each): a second process must find them in numba's cache (their closure
    constants pickle to the same key in every process) and add nothing to it. (The float64 fringe
    kernels are the float32 ones with other constants.)"""
    import subprocess
    import sys

    code = ("import json, numpy as np\n"
            "from mmflow.mmode import fringe_kernels as fk, legendre, spin_legendre\n"
            "legendre.legendre_table(3, 20, np.linspace(0.1, 3.0, 7))\n"
            "spin_legendre.weighted_spin_tables(3, 20, np.linspace(0.1, 3.0, 7))\n"
            "fk.sincos_turns(np.array([0.1, 0.4]), np.float32)\n"
            "v, k, out = np.ones((4, 3)) / 3 ** 0.5, np.ones((4, 2), complex), np.empty((2, 2, 5, 4), np.complex64)\n"
            "fk.kernel_fringe_folds(fk.ring_fringes(v, -v, np.ones((5, 3)), np.float32), k.T, k.T, out[0], out[1])\n"
            "ks = [legendre._kernel(), spin_legendre._kernel(), *fk._kernels('float32')]\n"
            "print(json.dumps([[len(k.stats.cache_hits), len(k.stats.cache_misses)] for k in ks]))\n")
    env = dict(__import__("os").environ, NUMBA_CACHE_DIR=str(tmp_path))

    def run():
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
        return __import__("json").loads(out.stdout.strip().splitlines()[-1])

    first = run()
    files = sorted(p.name for p in tmp_path.rglob("*.nb*"))
    assert first == [[0, 1]] * 5  # compiled once each, and written to the cache
    assert run() == [[1, 0]] * 5  # the second process compiles nothing
    assert sorted(p.name for p in tmp_path.rglob("*.nb*")) == files  # and adds no entry
