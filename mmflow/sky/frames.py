"""Rotations between the sky frame of date (astropy TETE at the epoch), ICRS and Galactic.

The transfer matrices and the m-mode transform live in the frame of date, where the
sidereal angle is the apparent local sidereal time. Maps are rotated to ICRS (default)
or Galactic on output; sources given in ICRS are rotated into the frame of date.
"""
import warnings
from functools import lru_cache

import ducc0
import erfa
import numpy as np
from astropy import units as u
from astropy.time import Time
from scipy.spatial.transform import Rotation

from mmflow.conventions import enu_to_equatorial_matrix
from mmflow.threads import n_threads


@lru_cache(maxsize=32)
def _matrix(src, dst, epoch_jd):
    # deferred: astropy.coordinates takes 0.1-0.2 s to import (docs/performance.md)
    from astropy.coordinates import ICRS, TETE, Galactic, SkyCoord

    t = Time(epoch_jd, format="jd", scale="utc")
    frames = {"icrs": ICRS(), "galactic": Galactic(), "date": TETE(obstime=t)}
    rng = np.random.default_rng(0)
    src_vec = rng.normal(size=(3, 64))
    src_vec /= np.linalg.norm(src_vec, axis=0)
    lon = np.arctan2(src_vec[1], src_vec[0])
    lat = np.arcsin(src_vec[2])
    c = SkyCoord(lon * u.rad, lat * u.rad, frame=frames[src])
    dst_vec = c.transform_to(frames[dst]).cartesian.xyz.value
    # best rigid rotation (orthogonal Procrustes); aberration makes the map slightly non-rigid
    uu, _, vt = np.linalg.svd(dst_vec @ src_vec.T)
    return uu @ vt


def rotation_matrix(src, dst, epoch_jd):
    """3x3 matrix R with ``v_dst = R @ v_src`` for frames ``'icrs'``, ``'galactic'``, ``'date'``.

    ``'date'`` is TETE (true equator and equinox of date) at ``epoch_jd`` (UTC Julian
    date); its RA zero point is the one the apparent sidereal time refers to.
    ``rotation_matrix(b, a, t)`` is exactly the transpose of ``rotation_matrix(a, b, t)``: each
    pair is fitted once, from the frame of date outwards (astropy's two directions differ by
    up to 3 arcsec for Galactic, through aberration; a map rotated out and back must come home).
    """
    if src == dst:
        return np.eye(3)
    if _FIT_ORDER.index(src) > _FIT_ORDER.index(dst):
        return _matrix(dst, src, float(epoch_jd)).T
    return _matrix(src, dst, float(epoch_jd))


_FIT_ORDER = ("date", "icrs", "galactic")


def apparent_sidereal_time(jd_utc, lon_deg):
    """Local apparent sidereal time (rad, in [0, 2 pi)) at UTC Julian dates ``jd_utc`` and east
    longitude ``lon_deg``: the sidereal angle of the frame of date.

    ``LAST = GAST(UT1, TT) + s' + lambda``: Greenwich apparent sidereal time of IAU 2006/2000A
    (ERFA ``gst06a``), the TIO locator ``s'`` (``sp00``) and the longitude; UT1 - UTC from astropy's
    IERS table, held at its ends outside it (offline: :mod:`mmflow.offline`). This is the definition
    of pyuvdata's ``lst_array`` (``pyuvdata.utils.get_lst_for_time``, ERFA library), to rounding
    (tested), without importing pyuvdata (2-3.5 s) in every worker that only needs the angle.
    """
    t = Time(np.atleast_1d(np.asarray(jd_utc, float)), format="jd", scale="utc")
    delta, status = t.get_delta_ut1_utc(return_status=True)
    if np.any(status < 0):  # iers.TIME_BEFORE_IERS_RANGE (-1), TIME_BEYOND_IERS_RANGE (-2)
        warnings.warn("times outside the IERS table: UT1 - UTC held at the table's end (as pyuvdata does)",
                      stacklevel=2)
    t.delta_ut1_utc = delta
    ut1, tt = t.ut1, t.tt
    gast = erfa.gst06a(ut1.jd1, ut1.jd2, tt.jd1, tt.jd2)
    return np.mod(gast + erfa.sp00(tt.jd1, tt.jd2) + np.deg2rad(lon_deg), 2.0 * np.pi)


def tangent_basis(vec):
    """East and north unit vectors on the sky at unit directions ``vec`` (..., 3), in their frame.

    ``e = z x r / |z x r|`` (towards increasing RA) and ``n = r x e``; at the poles, where
    ``z x r`` vanishes (``|z x r| < 1e-12``), ``e = +y`` and ``n = r x e``.
    """
    vec = np.asarray(vec, float)
    east = np.cross([0.0, 0.0, 1.0], vec)
    norm = np.linalg.norm(east, axis=-1, keepdims=True)
    pole = norm < 1e-12
    east = np.where(pole, [0.0, 1.0, 0.0], east / np.where(pole, 1.0, norm))
    return east, np.cross(vec, east)


def source_enu(telescope, lsts, vec_date):
    """ENU unit vectors (..., n_time, 3) of frame-of-date directions ``vec_date`` (..., 3).

    ``r_enu(t) = vec_date . R(lat, phi_t)`` with ``R`` of
    :func:`mmflow.conventions.enu_to_equatorial_matrix` (ENU -> frame of date) at the site's
    latitude ``telescope.lat_rad`` and each sidereal angle ``lsts`` (rad).
    """
    rots = np.stack([enu_to_equatorial_matrix(telescope.lat_rad, p) for p in np.atleast_1d(lsts)])
    return np.einsum("...k,tkl->...tl", np.asarray(vec_date, float), rots)


def rotate_alm(alm, matrix, lmax):
    """Rotate real-sky ``a_lm`` (healpy layout) so the map ``f(r)`` becomes ``f(R^T r)``.

    Equivalently: coefficients given in frame S become coefficients in frame D for
    ``matrix = rotation_matrix(S, D)``. With ZYZ Euler angles ``R = R_z(phi) R_y(theta) R_z(psi)``
    this is ducc0's Wigner-d rotation, equal to healpy's to ~1e-15 (``tests/unit/test_numerics.py``;
    its speed: ``docs/performance.md``). Verified by a point-source test.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # gimbal lock (theta = 0 or pi) is handled
        phi, theta, psi = Rotation.from_matrix(np.asarray(matrix, float)).as_euler("ZYZ")
    return ducc0.sht.rotate_alm(np.asarray(alm, np.complex128), lmax, psi, theta, phi, nthreads=n_threads())
