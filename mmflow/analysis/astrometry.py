"""Astrometric registration of a map against a source catalogue (paper section 4, optional product).

Positions
---------
Around each catalogue direction the brightest pixel within a search radius is found, the local
background (median of an annulus) removed, and the pixels within ``fit_radius`` of it fitted
by a quadratic in tangent-plane coordinates ``(x, y)``:

``ln f = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2``  (least squares, weights ``f^2``),

which is exact for an elliptical Gaussian main lobe whatever the pixelisation; the position is
the vertex ``H^-1 (-c1, -c2)`` with ``H = [[2 c3, c4], [c4, 2 c5]]``.

Registration
------------
A global rotation ``R`` (a small rigid "shift" on the sphere) taking catalogue directions
``c_i`` to measured ones ``m_i`` is the solution of Wahba's problem,
``min_R sum_i w_i |m_i - R c_i|^2``: with ``B = sum_i w_i m_i c_i^T = U S V^T``,
``R = U diag(1, 1, det(U V^T)) V^T``. ``axis="z"`` fits only a rotation about the pole (an RA
shift, e.g. a clock or sidereal-time error): ``tan(phi) = sum w (c x m)_z / sum w (c_xy . m_xy)``.
Offsets are reported before (``m_i`` vs ``c_i``) and after (``m_i`` vs ``R c_i``) registration.
"""
from __future__ import annotations

import healpy
import numpy as np

from mmflow.conventions import radec_to_vec


def _tangent(vecs, center):
    """Gnomonic tangent-plane coordinates (east, north) of ``vecs`` about ``center``."""
    z = np.array([0.0, 0.0, 1.0]) if abs(center[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    e = np.cross(z, center)
    e /= np.linalg.norm(e)
    n = np.cross(center, e)
    d = vecs @ center
    return (vecs @ e) / d, (vecs @ n) / d, e, n


def fit_position(hmap, vec, search_radius_rad, fit_radius_rad, annulus_rad=None):
    """Fitted position of the compact source nearest ``vec`` (see the module's equation).

    Parameters
    ----------
    hmap : ndarray, HEALPix (RING) map
    vec : (3,) catalogue direction (in the map's frame)
    search_radius_rad : the peak is searched within this distance of ``vec``
    fit_radius_rad : pixels within this distance of the peak are fitted (~0.5-0.7 FWHM)
    annulus_rad : (inner, outer) radii about the peak whose median is the background
        (default ``(3, 5) x fit_radius``)

    Returns
    -------
    dict with ``vec`` (fitted direction), ``peak`` (background-subtracted peak), ``offset_rad``
    (from ``vec``) and ``ok`` (False when the fit is not a maximum: the pixel centre is kept).
    """
    nside = healpy.npix2nside(len(hmap))
    vec = np.asarray(vec, float) / np.linalg.norm(vec)
    disc = healpy.query_disc(nside, vec, search_radius_rad)
    ipk = disc[np.argmax(hmap[disc])]
    c0 = np.array(healpy.pix2vec(nside, ipk))
    inner, outer = annulus_rad if annulus_rad is not None else (3 * fit_radius_rad, 5 * fit_radius_rad)
    ring = np.setdiff1d(healpy.query_disc(nside, c0, outer), healpy.query_disc(nside, c0, inner))
    background = float(np.median(hmap[ring])) if len(ring) else 0.0
    pix = healpy.query_disc(nside, c0, fit_radius_rad)
    f = hmap[pix] - background
    good = f > 0.05 * (hmap[ipk] - background)
    result = {"vec": c0, "peak": float(hmap[ipk] - background), "ok": False}
    if good.sum() >= 6:
        x, y, e, n = _tangent(np.array(healpy.pix2vec(nside, pix[good])).T, c0)
        s = healpy.nside2resol(nside)
        x, y = x / s, y / s
        a = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], 1)
        w = f[good]  # weights f^2 on ln f: the error of ln f is ~ noise / f
        coef = np.linalg.lstsq(a * w[:, None], np.log(f[good]) * w, rcond=None)[0]
        hess = np.array([[2 * coef[3], coef[4]], [coef[4], 2 * coef[5]]])
        if np.all(np.linalg.eigvalsh(hess) < 0):
            x0, y0 = np.linalg.solve(hess, -coef[1:3])
            if np.hypot(x0, y0) * s < fit_radius_rad:
                v = c0 + s * (x0 * e + y0 * n)
                result.update(vec=v / np.linalg.norm(v), ok=True,
                              peak=float(np.exp(coef[0] + 0.5 * (coef[1] * x0 + coef[2] * y0))))
    result["offset_rad"] = float(np.arccos(np.clip(result["vec"] @ vec, -1, 1)))
    return result


def fit_rotation(catalog_vecs, measured_vecs, weights=None, axis=None):
    """Rotation ``R`` minimising ``sum w |m - R c|^2`` (Wahba; ``axis="z"``: about the pole only)."""
    c = np.asarray(catalog_vecs, float)
    m = np.asarray(measured_vecs, float)
    w = np.ones(len(c)) if weights is None else np.asarray(weights, float)
    if axis == "z":
        num = np.sum(w * (c[:, 0] * m[:, 1] - c[:, 1] * m[:, 0]))
        den = np.sum(w * (c[:, 0] * m[:, 0] + c[:, 1] * m[:, 1]))
        phi = np.arctan2(num, den)
        cp, sp = np.cos(phi), np.sin(phi)
        return np.array([[cp, -sp, 0.0], [sp, cp, 0.0], [0.0, 0.0, 1.0]])
    if axis is not None:
        raise ValueError(f"axis must be None or 'z', not {axis!r}")
    u, _, vt = np.linalg.svd((m * w[:, None]).T @ c)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rotation_angle_axis(r):
    """Angle (rad) and unit axis of a rotation matrix."""
    angle = float(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    norm = np.linalg.norm(axis)
    return angle, (axis / norm if norm > 0 else np.array([0.0, 0.0, 1.0]))


def _sep(a, b):
    return np.arccos(np.clip(np.sum(a * b, axis=-1), -1, 1))


def register(hmap, catalog, search_radius_rad, fit_radius_rad, axis=None, rotation=None):
    """Fit every catalogue source, then the global rotation; offsets before and after.

    Parameters
    ----------
    catalog : list of :class:`mmflow.sky.sources.Source` or of ``(name, ra_deg, dec_deg)``
    rotation : 3x3, ICRS -> the map's frame (None: the map is ICRS)
    axis : None (any rotation) or ``"z"`` (about the pole)

    Returns
    -------
    dict with ``rows`` (one per source: name, fitted RA/Dec, offsets before/after in arcmin,
    ``ok``), ``rotation`` (3x3), ``rotation_arcmin``, ``axis``, ``rms_before_arcmin`` and
    ``rms_after_arcmin`` over the sources whose fit succeeded.
    """
    names, cat = [], []
    for s in catalog:
        if hasattr(s, "vector_icrs"):
            names.append(s.name)
            v = s.vector_icrs()
        else:
            names.append(s[0])
            v = radec_to_vec(np.deg2rad(s[1]), np.deg2rad(s[2]))
        cat.append(v if rotation is None else rotation @ v)
    cat = np.array(cat)
    fits = [fit_position(hmap, v, search_radius_rad, fit_radius_rad) for v in cat]
    ok = np.array([f["ok"] for f in fits])
    meas = np.array([f["vec"] for f in fits])
    if ok.sum() >= (1 if axis == "z" else 2):
        r = fit_rotation(cat[ok], meas[ok], axis=axis)
    else:
        r = np.eye(3)
    before, after = _sep(meas, cat), _sep(meas, cat @ r.T)
    angle, ax = rotation_angle_axis(r)
    to_arcmin = 60 * 180 / np.pi
    rows = []
    for i, (name, f) in enumerate(zip(names, fits)):
        lon, lat = healpy.vec2ang(f["vec"], lonlat=True)
        rows.append({"name": name, "ra_deg": float(lon[0]), "dec_deg": float(lat[0]), "peak": f["peak"],
                     "offset_before_arcmin": float(before[i] * to_arcmin),
                     "offset_after_arcmin": float(after[i] * to_arcmin), "ok": bool(f["ok"])})
    rms = lambda d: float(np.sqrt(np.mean(d[ok] ** 2)) * to_arcmin) if ok.any() else float("nan")  # noqa: E731
    return {"rows": rows, "rotation": r, "rotation_arcmin": angle * to_arcmin, "axis": ax.tolist(),
            "rms_before_arcmin": rms(before), "rms_after_arcmin": rms(after), "n_fitted": int(ok.sum())}


def registration_rows(result):
    """The report's rows and fit summary (plain JSON types) from :func:`register`."""
    fit = {k: result[k] for k in ("rotation_arcmin", "axis", "rms_before_arcmin", "rms_after_arcmin", "n_fitted")}
    return result["rows"], fit
