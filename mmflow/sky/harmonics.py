"""Spherical harmonics at arbitrary points, stable at any lmax.

Every place where a point (a source, a PSF probe, a CLEAN component) becomes ``a_lm``, or
``a_lm`` are evaluated at a few points, goes through this module. scipy's ``sph_harm_y``
overflows to NaN from l ~ 646 on (scipy 1.17), so it must not be used for that.

Method
------
ducc0's Legendre transforms (``ducc0.sht.leg2alm`` and ``alm2leg``) evaluate the normalised
associated Legendre functions ``lambda_lm(theta) = Y_lm(theta, 0)`` by a three-term recursion
in l with dynamic rescaling (no overflow or underflow at any l; tested here to l = 2000 and at
the poles, see ``tests/unit/test_numerics.py`` and ``docs/numerics.md``). The results are exact to
rounding (no NUFFT approximation): for a set of points ``k`` with colatitude ``theta_k`` and
longitude ``phi_k``,

``leg2alm``:  ``a_lm = sum_k lambda_lm(theta_k) L_k,m``  with ``L_k,m = f_k exp(-i m phi_k)``
gives ``a_lm = sum_k f_k conj(Y_lm(r_k))``;

``alm2leg``:  ``L_k,m = sum_l lambda_lm(theta_k) a_lm``, and the real sky at ``r_k`` is
``f(r_k) = Re L_k,0 + 2 Re sum_{m>0} L_k,m exp(i m phi_k)``.

Conventions (docs/conventions.md): healpy's alm layout (m-major) with ``mmax <= lmax``,
orthonormal ``Y_lm`` with the Condon-Shortley phase, real sky ``a_{l,-m} = (-1)^m conj(a_lm)``.
Cost: ``O(n_points * n_alm)`` (a measured time: docs/performance.md).
"""
from __future__ import annotations

import ducc0
import numpy as np

from mmflow.threads import n_threads

_CHUNK = 512  # points per Legendre transform (bounds the (points, m) work array to ~8 MB)


def _mmax(lmax, mmax):
    mmax = lmax if mmax is None else int(mmax)
    if not 0 <= mmax <= lmax:
        raise ValueError(f"mmax must satisfy 0 <= mmax <= lmax, got mmax={mmax}, lmax={lmax}")
    return mmax


def _layout(lmax, mmax):
    """``mval``, ``mstart`` of healpy's layout and its size for (lmax, mmax)."""
    m = np.arange(mmax + 1)
    mstart = (m * (2 * lmax + 1 - m)) // 2
    size = (mmax + 1) * (lmax + 1) - (mmax * (mmax + 1)) // 2
    return m.astype(np.uintp), mstart.astype(np.uintp), size


def _angles(vecs):
    """Colatitude and longitude of (n, 3) vectors (normalised here; any frame)."""
    v = np.atleast_2d(np.asarray(vecs, float))
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vecs must have shape (n, 3), got {np.shape(vecs)}")
    norm = np.linalg.norm(v, axis=1)
    if not np.all(np.isfinite(norm)) or np.any(norm == 0):
        raise ValueError("vecs must be finite, non-zero vectors")
    v = v / norm[:, None]
    theta = np.arctan2(np.hypot(v[:, 0], v[:, 1]), v[:, 2])  # accurate near the poles too
    phi = np.arctan2(v[:, 1], v[:, 0]) % (2 * np.pi)
    return theta, phi


def point_sources_alm(vecs, fluxes, lmax, mmax=None, mmin=0):
    """``a_lm`` of a sum of delta functions: ``a_lm = sum_k flux_k conj(Y_lm(vec_k))``.

    This is the harmonic transform of ``sum_k flux_k delta(r - vec_k)`` (a point-source sky
    in Jy gives ``a_lm`` in Jy/sr units of the brightness expansion).

    Parameters
    ----------
    vecs : array_like, shape (n, 3)
        Directions (normalised here), in the frame the ``a_lm`` are wanted in.
    fluxes : array_like, shape (n,)
        Real weights ``flux_k``.
    lmax, mmax : int
        Band limit; ``mmax`` defaults to ``lmax``.
    mmin : int
        Only ``m >= mmin`` (an m block of a CLEAN cycle): the coefficients are those of the full
        layout from ``(l, m) = (mmin, mmin)`` on, each the same to the bit (every m is its own
        recursion in l).

    Returns
    -------
    ndarray, complex128, healpy layout of size ``Alm.getsize(lmax, mmax)`` (with ``mmin``: its part
    from ``(mmin, mmin)`` on)
    """
    mmax = _mmax(lmax, mmax)
    if not 0 <= mmin <= mmax:
        raise ValueError(f"mmin must satisfy 0 <= mmin <= mmax, got mmin={mmin}, mmax={mmax}")
    theta, phi = _angles(vecs)
    fluxes = np.broadcast_to(np.asarray(fluxes, float), theta.shape)
    return _conj_ylm_sum(theta, phi, fluxes, lmax, mmax, mmin)


def _conj_ylm_sum(theta, phi, weights, lmax, mmax, mmin=0):
    """``sum_k weights_k conj(Y_lm(theta_k, phi_k))`` in healpy layout from ``m = mmin`` on (ducc0
    ``leg2alm``; its ``mstart`` indices must be >= 0: the output is computed ``mmin`` places into a
    buffer whose first ``mmin`` entries no ``l >= m`` reaches)."""
    mval, mstart, size = _layout(lmax, mmax)
    skip = int(mstart[mmin]) + mmin  # the index of (l, m) = (mmin, mmin) in the full layout
    mval, mstart = mval[mmin:], mstart[mmin:] - (skip - mmin)
    alm = np.zeros((1, size - skip + mmin), np.complex128)
    m = np.arange(mmin, mmax + 1)
    for s in range(0, len(theta), _CHUNK):
        sl = slice(s, s + _CHUNK)
        leg = (weights[sl, None] * np.exp(-1j * m[None, :] * phi[sl, None]))[None]
        alm += ducc0.sht.leg2alm(leg=leg, lmax=lmax, theta=theta[sl], spin=0, mval=mval,
                                 mstart=mstart, nthreads=n_threads())
    return alm[0, mmin:]


def synthesize_at(alm, vecs, lmax, mmax=None):
    """The real sky ``f(r_k) = sum_{l, |m| <= l} a_lm Y_lm(r_k)`` at the points ``vecs``.

    ``alm`` holds ``m >= 0`` of a real sky (``a_{l,-m} = (-1)^m conj(a_lm)``), so
    ``f = sum_l [a_l0 Y_l0 + 2 Re sum_{m>0} a_lm Y_lm]``. This is the adjoint of
    :func:`point_sources_alm` under the real-sky inner product
    ``<a, b> = sum_{l, all m} conj(a_lm) b_lm``:
    ``<point_sources_alm(vecs, f), b> = f . synthesize_at(b, vecs)``.

    Returns
    -------
    ndarray, float64, shape (n,)
    """
    mmax = _mmax(lmax, mmax)
    theta, phi = _angles(vecs)
    mval, mstart, size = _layout(lmax, mmax)
    alm = np.asarray(alm, np.complex128)
    if alm.shape != (size,):
        raise ValueError(f"alm must have shape ({size},) for lmax={lmax}, mmax={mmax}, got {alm.shape}")
    m = np.arange(mmax + 1)
    weight = np.where(m > 0, 2.0, 1.0)
    out = np.empty(len(theta))
    for s in range(0, len(theta), _CHUNK):
        sl = slice(s, s + _CHUNK)
        leg = ducc0.sht.alm2leg(alm=alm[None], lmax=lmax, theta=theta[sl], spin=0, mval=mval,
                                mstart=mstart, nthreads=n_threads())[0]
        out[sl] = (leg * np.exp(1j * m[None, :] * phi[sl, None])).real @ weight
    return out


def ylm_at(vecs, lmax, mmax=None):
    """``Y_lm(vec_k)`` for ``0 <= m <= mmax``, ``m <= l <= lmax``: shape (n_points, n_alm).

    Rows follow healpy's alm layout. Memory is ``16 n_points n_alm`` bytes, so this is for a
    few points (tests, probes); use :func:`point_sources_alm` for sums over many points.
    """
    theta, phi = _angles(vecs)
    mmax = _mmax(lmax, mmax)
    _, _, size = _layout(lmax, mmax)
    out = np.empty((len(theta), size), np.complex128)
    for k in range(len(theta)):
        out[k] = np.conj(_conj_ylm_sum(theta[k:k + 1], phi[k:k + 1], np.ones(1), lmax, mmax))
    return out
