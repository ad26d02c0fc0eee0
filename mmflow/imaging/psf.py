"""Point spread function of Tikhonov-regularised m-mode maps (paper section 2.4, eq. psf).

The map of a sky ``x`` (alm, frame of date) made from noiseless data ``v = B x`` is, per m,

``y_k = (G_kk + eps I)^-1 (G x)_k``,   ``y_f = 0``,

where ``G = B^H N^-1 B`` is block m's Gram, ``k`` the coefficients kept by the m-filters
(:func:`mmflow.imaging.filters.filter_mask`: ``a_00``, ``m = 0`` and ``m = 1, l > 100`` removed)
and ``f`` the filtered ones. This is "observing" ``x``: it is linear, block-diagonal in m and
evaluated right to left through the Cholesky factor ``G_kk + eps I = U^H U``
(``U^-1 U^-H G x``, eq. rapid-psf). Since ``(G_kk + eps I)^-1 G_kk = I - eps (G_kk + eps I)^-1``,

``y_k = x_k - eps U^-1 U^-H x_k + U^-1 U^-H G_kf x_f``,

so a block operator only keeps ``U`` and, for the few blocks with filtered coefficients
(``m = 1``), the coupling ``G_kf``: half the memory and work of keeping ``G`` too.

The PSF at ``r0`` is the observed point source ``x = conj(Y_lm(r0))`` (eq. psf). It depends only
on declination: moving the source by ``dphi`` in RA multiplies ``x_lm`` by ``exp(-i m dphi)``
and the operator is diagonal in m, so the PSF rotates rigidly.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import healpy
import numpy as np
import scipy.linalg as sla

from mmflow.conventions import alm_index, m_block_slice, radec_to_vec
from mmflow.imaging.filters import filter_mask
from mmflow.errors import InputError
from mmflow.sky.frames import tangent_basis
from mmflow.sky.harmonics import point_sources_alm, synthesize_at
from mmflow.threads import n_threads, single_threaded_blas

FWHM_PER_SIGMA = np.sqrt(8 * np.log(2))


# ----------------------------------------------------------------------------- observing

def map_blocks(fn, items, threads=None):
    """``[fn(i) for i in items]`` on ``n_threads()`` threads, each with single-threaded BLAS.

    m blocks are independent and LAPACK releases the GIL: threads over blocks, each with one
    BLAS thread, never wait on each other, where one multi-threaded LAPACK call per block has
    its OpenBLAS threads stall at every synchronisation when a core is taken away
    (``docs/performance.md``).
    """
    items = list(items)
    threads = n_threads() if threads is None else threads
    with single_threaded_blas():
        if threads <= 1 or len(items) <= 1:
            return [fn(i) for i in items]

        with ThreadPoolExecutor(threads) as ex:
            return list(ex.map(fn, items))


def observe(cho, gram, x_block, keep):
    """``y_k = (G_kk + eps I)^-1 (G x)_k``, ``y_f = 0`` for one m block (direct form).

    Parameters
    ----------
    cho : tuple
        ``scipy.linalg.cho_factor`` of ``G_kk + eps I`` (as returned by
        :func:`mmflow.imaging.solvers.tikhonov`).
    gram : ndarray (n, n)
        The full Hermitian Gram of the block, ``n = lmax - m + 1`` (all l, filtered too).
    x_block : ndarray (n,) or (n, k)
        Sky coefficients ``a_lm``, ``l = m..lmax`` (one or several columns).
    keep : ndarray (n,) bool
        Coefficients kept by the m-filters.
    """
    x = np.asarray(x_block)
    y = np.zeros(x.shape, np.result_type(x.dtype, gram.dtype, np.complex64))
    if keep.any():
        y[keep] = sla.cho_solve(cho, gram[keep] @ x, check_finite=False)
    return y


@dataclass
class BlockOperator:
    """What observing needs for one m block: ``U`` of ``G_kk + eps I`` and ``G_kf``.

    Attributes
    ----------
    m : int
    keep : ndarray (n,) bool
    cho : tuple or None
        ``cho_factor`` of ``G_kk + eps I``; None when nothing is kept (``m = 0`` filtered).
    eps : float
    coupling : ndarray (n_kept, n_filtered) or None
        ``G_kf``; None when every coefficient is kept.
    """

    m: int
    keep: np.ndarray
    cho: tuple | None
    eps: float
    coupling: np.ndarray | None = None

    @property
    def nbytes(self):
        n = 0 if self.cho is None else self.cho[0].nbytes
        return n + (0 if self.coupling is None else self.coupling.nbytes)


def block_operator(m, gram, eps, keep):
    """Factor ``G_kk + eps I`` (Cholesky) and keep ``G_kf`` for the filtered columns."""
    keep = np.asarray(keep, bool)
    if not keep.any():
        return BlockOperator(m, keep, None, eps)
    if eps <= 0:
        raise InputError("imaging", "eps", f"eps={eps} must be > 0 for a Cholesky factor",
                         "use a positive eps")
    gkk = np.array(gram if keep.all() else gram[np.ix_(keep, keep)], order="F", copy=True)
    gkk[np.diag_indices(len(gkk))] += eps
    cho = sla.cho_factor(gkk, lower=False, overwrite_a=True, check_finite=False)
    coupling = None if keep.all() else np.ascontiguousarray(gram[np.ix_(keep, ~keep)])
    return BlockOperator(m, keep, cho, eps, coupling)


def observe_block(op, x_block):
    """Observe one block through its :class:`BlockOperator` (same result as :func:`observe`)."""
    x = np.asarray(x_block)
    y = np.zeros(x.shape, np.result_type(x.dtype, np.complex64))
    if op.cho is None:
        return y
    xk = x[op.keep]
    yk = xk - op.eps * sla.cho_solve(op.cho, xk, check_finite=False)
    if op.coupling is not None:
        yk = yk + sla.cho_solve(op.cho, op.coupling @ x[~op.keep], check_finite=False)
    y[op.keep] = yk
    return y


def block_operators(acc, eps, filters=None, ms=None):
    """:class:`BlockOperator` for each m of a :class:`~mmflow.mmode.normal.NormalAccumulator`.

    ``filters`` are :func:`~mmflow.imaging.filters.filter_mask` keywords (None: the paper's);
    use the same ones as the dirty map so that the PSF carries the filter's NCP rings.
    """
    filters = {} if filters is None else filters
    ms = list(acc.ms if ms is None else ms)
    ops = map_blocks(lambda m: block_operator(m, acc.full_gram(m), eps, filter_mask(m, acc.lmax, **filters)), ms)
    return dict(zip(ms, ops))


def observe_alm(ops, alm, lmax):
    """Observe a full healpy-layout alm vector (or ``(n_alm, k)`` columns) block by block.

    Blocks without an operator (m beyond the data's mmax) observe to zero.
    """
    return observe_range(ops, alm, lmax, 0, lmax + 1)


def observe_range(ops, x_block, lmax, m_start, m_stop, weights=None):
    """Observe the ``m_start <= m < m_stop`` part of an alm (:func:`mmflow.conventions.m_block_slice` of it).

    ``x_block`` (n,) or (n, k) columns; m without an operator observe to zero (no data
    constrain them); ``weights`` (over l = 0..lmax) multiply the result (a high-pass CLEAN's
    ``H observe``). This is the one observing loop: the PSF, CLEAN's subtraction and the
    workflow's m-block tasks all call it.
    """
    x = np.asarray(x_block)
    out = np.zeros(x.shape, np.complex128)
    base = alm_index(lmax, m_start, m_start)

    def one(m):
        s = alm_index(lmax, m, m) - base
        sl = slice(s, s + lmax - m + 1)
        y = observe_block(ops[m], x[sl])
        if weights is not None:
            w = np.asarray(weights)[m:]
            y = y * (w if y.ndim == 1 else w[:, None])
        out[sl] = y

    map_blocks(one, [m for m in range(m_start, min(m_stop, lmax + 1)) if m in ops])
    return out


# ----------------------------------------------------------------------------- PSF alm

def point_columns(vecs, lmax, m_stop=None, m_start=0):
    """``conj(Y_lm(r_k))`` for each direction, as columns ``(n, k)`` of the healpy layout up to
    ``m < m_stop`` (default all m): the sky of a 1 Jy point source (eq. psf's ``a_PS``). With ``m_start``
    only the rows of ``m >= m_start`` (:func:`mmflow.conventions.m_block_slice`), the same bits: each m is
    its own recursion in l (:func:`mmflow.sky.harmonics.point_sources_alm`)."""
    v = np.atleast_2d(np.asarray(vecs, float))
    mmax = lmax if m_stop is None else min(lmax, m_stop - 1)
    return np.stack([point_sources_alm(vk[None], [1.0], lmax, mmax, m_start) for vk in v], axis=1)


def psf_alm(ops, lmax, vecs):
    """``a_PSF = observe(conj(Y_lm(r0)))`` for one direction (n_alm,) or several (n_alm, k)."""
    out = observe_alm(ops, point_columns(vecs, lmax), lmax)
    return out[:, 0] if np.ndim(vecs) == 1 else out


def psf_columns(ops, lmax, vecs, m_start=0, m_stop=None, weights=None, batch=16):
    """The ``m_start <= m < m_stop`` part of the PSFs at ``vecs``, ``(n, k)`` (rows: the
    :func:`mmflow.conventions.m_block_slice` of the healpy alm vector).

    Observed ``batch`` columns at a time; ``weights``: the PSF of a high-pass CLEAN,
    ``H observe(a_PS)``. The workflow's m-block tasks call this per block; :func:`psf_table`
    calls it for all m.
    """
    m_stop = lmax + 1 if m_stop is None else m_stop
    vecs = np.atleast_2d(np.asarray(vecs, float))
    sl = m_block_slice(lmax, m_start, m_stop)
    out = np.zeros((sl.stop - sl.start, len(vecs)), np.complex128)
    for s in range(0, len(vecs), batch):
        cols = point_columns(vecs[s:s + batch], lmax, m_stop, m_start)  # the block's m alone
        out[:, s:s + batch] = observe_range(ops, cols, lmax, m_start, m_stop, weights)
    return out


def value_at(alm, lmax, vec):
    """The real sky of ``alm`` at one direction."""
    return float(synthesize_at(alm, np.asarray(vec, float)[None], lmax)[0])


# ----------------------------------------------------------------------------- beam fitting

def tangent_frame(vec):
    """``(c, e, n)``: the unit vector ``c = vec / |vec|`` and the east and north unit vectors
    there (:func:`mmflow.sky.frames.tangent_basis`; at the poles e = +y)."""
    c = np.asarray(vec, float) / np.linalg.norm(vec)
    return (c, *tangent_basis(c))


def to_tangent(vecs, center):
    """Azimuthal-equidistant (x east, y north) coordinates in radians of ``vecs`` about ``center``."""
    c, e, n = tangent_frame(center)
    v = np.atleast_2d(vecs)
    xe, yn, z = v @ e, v @ n, v @ c
    rho = np.arctan2(np.hypot(xe, yn), z)
    s = np.hypot(xe, yn)
    scale = np.where(s > 0, rho / np.where(s > 0, s, 1), 1.0)
    return xe * scale, yn * scale


def from_tangent(x, y, center):
    """Unit vectors at azimuthal-equidistant offsets ``(x, y)`` (radians) from ``center``."""
    c, e, n = tangent_frame(center)
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    rho = np.hypot(x, y)
    sinc = np.where(rho > 0, np.sin(rho) / np.where(rho > 0, rho, 1), 1.0)
    return (np.cos(rho)[..., None] * c + (sinc * x)[..., None] * e + (sinc * y)[..., None] * n)


def fit_elliptical_gaussian(x, y, values, level=0.5):
    """Elliptical Gaussian fitted to the samples above ``level`` of the peak sample.

    Least squares of ``ln f = c0 + c1 x + c2 y + c3 x^2 + c4 xy + c5 y^2`` over the half-power
    region (exact for a Gaussian): the precision matrix is ``P = -[[2 c3, c4], [c4, 2 c5]]``,
    ``sigma_major = 1 / sqrt(min eig P)``, ``FWHM = sqrt(8 ln 2) sigma``; the position angle
    is that of the major axis, from north through east, in ``[0, pi)``.

    Returns
    -------
    dict: ``major``, ``minor``, ``pa`` (radians), ``peak``, ``x0``, ``y0`` (vertex offset).
    """
    x, y, f = (np.ravel(a) for a in (x, y, values))
    sel = f >= level * f.max()
    if sel.sum() < 6:
        raise ValueError("fewer than 6 samples above half power: sample the main lobe more finely")
    xs, ys = x[sel], y[sel]
    a = np.stack([np.ones_like(xs), xs, ys, xs * xs, xs * ys, ys * ys], axis=1)
    scale = np.abs(a).max(axis=0)
    c = np.linalg.lstsq(a / scale, np.log(f[sel]), rcond=None)[0] / scale
    p = -np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    w, v = np.linalg.eigh(p)
    if w[0] <= 0:
        raise ValueError("the half-power region is not a peak (non-negative curvature)")
    x0, y0 = np.linalg.solve(p, c[1:3])
    major_vec = v[:, 0]
    pa = np.arctan2(major_vec[0], major_vec[1]) % np.pi
    log_peak = c[0] + 0.5 * (c[1] * x0 + c[2] * y0)
    return {"major": FWHM_PER_SIGMA / np.sqrt(w[0]), "minor": FWHM_PER_SIGMA / np.sqrt(w[1]),
            "pa": float(pa), "peak": float(np.exp(log_peak)), "x0": float(x0), "y0": float(y0)}


def _half_power_radius(evaluate, center, r_guess, n=48, n_dir=8):
    """Largest distance along ``n_dir`` cuts at which ``evaluate`` first falls below half."""
    peak = evaluate(np.asarray(center, float)[None])[0]
    r = r_guess
    for _ in range(8):
        ang = np.arange(n_dir) * np.pi / n_dir
        rad = np.linspace(0, r, n + 1)[1:]
        x = np.concatenate([rad * np.sin(a) for a in ang] + [-rad * np.sin(a) for a in ang])
        y = np.concatenate([rad * np.cos(a) for a in ang] + [-rad * np.cos(a) for a in ang])
        vals = evaluate(from_tangent(x, y, center)).reshape(2 * n_dir, n)
        below = vals < 0.5 * peak
        if below.any(axis=1).all():
            first = np.argmax(below, axis=1)
            return float(rad[first].max())
        r *= 2
    raise ValueError("no half-power point within the search radius: is this a peak?")


def measure_beam(evaluate, center, r_guess, n_grid=41):
    """FWHM (major, minor), position angle and peak of the lobe centred near ``center``.

    ``evaluate(vecs) -> values`` samples the function (a PSF's alm, an analytic beam); a square
    patch of ``n_grid^2`` samples, 1.3 times the largest half-power radius found along radial
    cuts, is fitted by :func:`fit_elliptical_gaussian`. Angles in radians.
    """
    r_half = _half_power_radius(evaluate, center, r_guess)
    w = 1.3 * r_half
    g = np.linspace(-w, w, n_grid)
    x, y = np.meshgrid(g, g)
    vals = evaluate(from_tangent(x.ravel(), y.ravel(), center).reshape(-1, 3))
    return fit_elliptical_gaussian(x.ravel(), y.ravel(), vals)


def measure_psf(alm, lmax, vec, n_grid=41):
    """:func:`measure_beam` of a PSF given as alm; also ``value`` = the PSF at ``vec`` itself."""
    out = measure_beam(lambda v: synthesize_at(alm, v, lmax), vec, 2 * np.pi / max(lmax, 1), n_grid)
    out["value"] = value_at(alm, lmax, vec)
    return out


def highpass_weights(lmax, l_cut, l_width):
    """``w_l``: 0 below ``l_cut - l_width``, a cosine ramp to 1 at ``l_cut``, 1 above.

    CLEANing ``H a`` (``H = diag(w_l)``, diagonal in l and so per m block) leaves the smooth
    large-scale sky out of CLEAN (the reference CLEANs such a high-pass residual).
    """
    ell = np.arange(lmax + 1, dtype=float)
    x = np.clip((ell - (l_cut - l_width)) / max(l_width, 1e-9), 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


def apply_l_weights(alm, lmax, weights, out=None):
    """``w_l a_lm`` for a healpy-layout alm (``alm`` may have trailing columns); ``out``: where it goes
    (``alm`` itself weights in place: at lmax 1000 the PSF table's columns are 0.6 GB)."""
    ell = healpy.Alm.getlm(lmax)[0]
    w = np.asarray(weights)[ell]
    return np.multiply(alm, w if np.ndim(alm) == 1 else w[:, None], out=out)


def table_vectors(dec_rad, ra_rad=0.0):
    """Directions of a PSF table's sources: ``(ra, dec)`` for each declination."""
    dec = np.asarray(dec_rad, float)
    return radec_to_vec(np.full(len(dec), ra_rad), dec)


def fit_psf_columns(cols, lmax, dec_rad, ra_rad=0.0, n_grid=41):
    """PSF table from PSF alm columns ``(n_alm, n_dec)`` (one per declination, at ``ra_rad``).

    Returns
    -------
    dict of arrays over ``dec``: ``dec`` (rad), ``peak`` (PSF at the source, Jy/sr per Jy),
    ``major``, ``minor`` (FWHM, rad), ``pa`` (rad, north through east). Declinations where
    the PSF has no measurable main lobe get NaN widths and their value at the source.
    """
    dec = np.asarray(dec_rad, float)
    out = {k: np.full(len(dec), np.nan) for k in ("peak", "major", "minor", "pa")}
    out["dec"] = dec
    vecs = table_vectors(dec, ra_rad)
    for k in range(len(dec)):
        out["peak"][k] = value_at(cols[:, k], lmax, vecs[k])
        try:
            fit = measure_psf(cols[:, k], lmax, vecs[k], n_grid)
        except ValueError:
            continue
        out["major"][k], out["minor"][k], out["pa"][k] = fit["major"], fit["minor"], fit["pa"]
    return out


def psf_table(ops, lmax, dec_rad, ra_rad=0.0, batch=16, n_grid=41, weights=None):
    """PSF peak and fitted beam on a declination grid (the PSF depends only on declination).

    :func:`psf_columns` for all m, then :func:`fit_psf_columns` (see there for the result).
    ``weights``: the PSF of a high-pass CLEAN (:func:`highpass_weights`).
    """
    cols = psf_columns(ops, lmax, table_vectors(dec_rad, ra_rad), weights=weights, batch=batch)
    return fit_psf_columns(cols, lmax, dec_rad, ra_rad, n_grid)


TABLE_KEYS = ("dec", "peak", "major", "minor", "pa")


def table_to_array(table):
    """A PSF table as an ``(n_dec, 5)`` array (columns :data:`TABLE_KEYS`), for a store."""
    return np.stack([np.asarray(table[k], float) for k in TABLE_KEYS], axis=1)


def table_from_array(arr):
    """Inverse of :func:`table_to_array`."""
    a = np.asarray(arr, float)
    return {k: a[:, i].copy() for i, k in enumerate(TABLE_KEYS)}


def interp_table(table, dec_rad, key):
    """Linear interpolation of a :func:`psf_table` column in declination (PA through 2 PA)."""
    d = np.asarray(dec_rad, float)
    ok = np.isfinite(table[key])
    if key == "pa":
        c = np.interp(d, table["dec"][ok], np.cos(2 * table["pa"][ok]))
        s = np.interp(d, table["dec"][ok], np.sin(2 * table["pa"][ok]))
        return (0.5 * np.arctan2(s, c)) % np.pi
    return np.interp(d, table["dec"][ok], table[key][ok])


def gaussian_solid_angle(major, minor):
    """Solid angle of an elliptical Gaussian beam, ``pi / (4 ln 2) major minor`` (FWHMs, rad)."""
    return np.pi / (4 * np.log(2)) * major * minor
