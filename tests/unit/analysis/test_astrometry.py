"""Astrometric registration: fitted source positions and the global rotation of a map whose
sources are displaced from the catalogue by a known small rotation."""
import healpy
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mmflow.analysis.astrometry import fit_position, fit_rotation, register, registration_rows, rotation_angle_axis
from mmflow.sky.sources import CATALOG

NSIDE = 256  # 0.23 deg pixels
FWHM = np.deg2rad(1.5)


def gaussian_map(vecs, fluxes, rng, noise=0.0):
    """Elliptical Gaussians (FWHM 1.5 x 1.2 deg, position angles varying) on a smooth background."""
    npix = healpy.nside2npix(NSIDE)
    x, y, z = healpy.pix2vec(NSIDE, np.arange(npix))
    hmap = 50.0 + 20.0 * z + 10.0 * x + noise * rng.normal(size=npix)
    for k, (v, s) in enumerate(zip(vecs, fluxes)):
        pix = healpy.query_disc(NSIDE, v, 4 * FWHM)
        p = np.array(healpy.pix2vec(NSIDE, pix)).T
        e = np.cross([0.0, 0.0, 1.0], v)
        e /= np.linalg.norm(e)
        n = np.cross(v, e)
        pa = 0.4 * k
        a, b = np.cos(pa) * n + np.sin(pa) * e, -np.sin(pa) * n + np.cos(pa) * e
        sa, sb = FWHM / 2.3548, 0.8 * FWHM / 2.3548
        hmap[pix] += s * np.exp(-0.5 * ((p @ a / sa) ** 2 + (p @ b / sb) ** 2))
    return hmap


def catalog_vecs():
    return list(CATALOG.values()), np.array([s.vector_icrs() for s in CATALOG.values()])


def test_positions_and_rotation_recovered_within_0p05_fwhm():
    rng = np.random.default_rng(7)
    srcs, cat = catalog_vecs()
    true_rot = Rotation.from_rotvec(np.deg2rad(0.4) * np.array([0.3, -0.5, 0.81]) / 1.0).as_matrix()
    true_pos = cat @ true_rot.T
    hmap = gaussian_map(true_pos, rng.uniform(200, 1000, len(cat)), rng, noise=2.0)
    fits = [fit_position(hmap, v, np.deg2rad(1.5), 0.6 * FWHM) for v in cat]
    err = np.arccos(np.clip(np.sum(np.array([f["vec"] for f in fits]) * true_pos, 1), -1, 1))
    assert all(f["ok"] for f in fits)
    assert err.max() < 0.05 * FWHM, np.rad2deg(err.max()) * 60
    out = register(hmap, srcs, np.deg2rad(1.5), 0.6 * FWHM)
    angle, axis = rotation_angle_axis(out["rotation"] @ true_rot.T)  # residual rotation
    assert angle < 0.02 * FWHM
    assert out["rotation_arcmin"] == pytest.approx(0.4 * 60 * np.linalg.norm([0.3, -0.5, 0.81]), rel=0.03)
    assert out["rms_before_arcmin"] > 15 and out["rms_after_arcmin"] < 0.05 * np.rad2deg(FWHM) * 60
    print(f"max position error {np.rad2deg(err.max()) * 60:.3f} arcmin (FWHM 90 arcmin); residual rotation "
          f"{np.rad2deg(angle) * 60:.3f} arcmin; rms before/after {out['rms_before_arcmin']:.2f} / "
          f"{out['rms_after_arcmin']:.3f} arcmin")
    rows, fit = registration_rows(out)
    assert len(rows) == len(srcs) and fit["n_fitted"] == len(srcs)
    assert max(r["offset_after_arcmin"] for r in rows) < 0.05 * np.rad2deg(FWHM) * 60


def test_ra_shift_about_the_pole():
    rng = np.random.default_rng(8)
    srcs, cat = catalog_vecs()
    dphi = np.deg2rad(0.25)  # e.g. a 1-minute sidereal-time error
    rz = Rotation.from_euler("z", dphi).as_matrix()
    hmap = gaussian_map(cat @ rz.T, np.full(len(cat), 500.0), rng)
    out = register(hmap, srcs, np.deg2rad(1.5), 0.6 * FWHM, axis="z")
    angle, axis = rotation_angle_axis(out["rotation"])
    assert angle == pytest.approx(dphi, rel=0.02) and axis[2] == pytest.approx(1.0)
    assert out["rms_after_arcmin"] < 0.02 * np.rad2deg(FWHM) * 60


def test_fit_rotation_is_exact_for_noiseless_vectors():
    rng = np.random.default_rng(9)
    c = rng.normal(size=(6, 3))
    c /= np.linalg.norm(c, axis=1)[:, None]
    r = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix()
    np.testing.assert_allclose(fit_rotation(c, c @ r.T), r, atol=1e-12)
    assert np.linalg.det(fit_rotation(c, c @ r.T)) == pytest.approx(1.0)
