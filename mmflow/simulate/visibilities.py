"""Drift-scan visibilities straight from the measurement equation (paper eq. 1).

``V_ij(phi) = int A(r) I(r) exp(2 pi i (x_j - x_i) . r / lambda) dOmega``

evaluated for each sidereal angle ``phi`` in the local ENU frame, with 3-D antenna
positions. The sky is a set of weighted directions in the frame of date (point sources,
HEALPix pixels, or Gauss-Legendre nodes of a band-limited a_lm sky). As in matvis, the
per-antenna factors ``z_ap = exp(2 pi i x_a . r_p / lambda) = C + i S`` are formed once per
time and all baselines come from one symmetric rank-k product: with ``P = [C; S]`` and
``Q = P W P^T`` (BLAS ``?syrk``), ``V = conj(Z) W Z^T`` has ``Re V = Q_CC + Q_SS`` and
``Im V = Q_CS - Q_CS^T``. A few baselines of a large array (a corner turn's chunk) are computed
pair-wise instead (:func:`few_pairs`): ``conj(Z_A) W Z_B^T`` between the antennas at their two ends.
This module deliberately shares no code with :mod:`mmflow.mmode` so it can check it.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import ducc0
import healpy
import numpy as np
from scipy.linalg import blas

from mmflow.conventions import enu_to_equatorial_matrix, unit_vectors, complex_dtype
from mmflow.errors import InputError
from mmflow.conventions import SPEED_OF_LIGHT
from mmflow.threads import n_threads, single_threaded_blas


#: skies of at most this many points (a calibration model of point sources) are summed per baseline
#: (:func:`_simulate_points`): the rank-k product's (2 n_ant)^2 matrix costs nearly the same for one
#: point as for ten (measured at 256 antennas, 256 time steps, one thread: one point 0.05 s against
#: 0.17 s, eight points 0.12 s against 0.19 s)
FEW_POINTS = 8
SERIAL_WORK = 2_000_000  # time steps x points x antennas^2 below which one thread does the work
PIXEL_BLOCK = 1024  # directions per block: a block's phasors stay in a core's L2 cache
TIME_BLOCK = 64  # time steps per batched product of :func:`_simulate_pairs`


@dataclass
class SkyPoints:
    """Directions (frame of date) with flux weights in Jy: ``sum_p flux_p delta(r - r_p)``."""

    vectors: np.ndarray  # (n, 3)
    flux_jy: np.ndarray  # (n,)

    def __add__(self, other):
        return SkyPoints(np.concatenate([self.vectors, other.vectors]),
                         np.concatenate([self.flux_jy, other.flux_jy]))


def healpix_points(hpx_map_jy_sr):
    """Pixels of a HEALPix map (Jy/sr, frame of date) as weighted directions (pixel quadrature)."""
    npix = len(hpx_map_jy_sr)
    nside = healpy.npix2nside(npix)
    vec = np.array(healpy.pix2vec(nside, np.arange(npix))).T
    return SkyPoints(vec, np.asarray(hpx_map_jy_sr, float) * 4 * np.pi / npix)


def gauss_legendre_shape(quad_lmax):
    """``(ntheta, nphi)`` of the Gauss-Legendre grid :func:`gauss_legendre_points` samples a sky on to be
    exact to ``quad_lmax`` (one ring and one meridian more than the minimum)."""
    return quad_lmax // 2 + 2, quad_lmax + 2


def gauss_legendre_points(alm_jy_sr, lmax, quad_lmax):
    """A band-limited sky (a_lm, Jy/sr) sampled on a Gauss-Legendre grid exact to ``quad_lmax``.

    The quadrature ``sum_p w_p I(r_p) f(r_p)`` is exact for integrands of total band
    limit ``<= quad_lmax`` (``ntheta = quad_lmax // 2 + 1``, ``nphi = quad_lmax + 1``).
    """
    ntheta, nphi = gauss_legendre_shape(quad_lmax)
    sky = ducc0.sht.synthesis_2d(alm=np.asarray(alm_jy_sr, np.complex128)[None], spin=0, lmax=lmax,
                                 geometry="GL", ntheta=ntheta, nphi=nphi)[0]
    theta = ducc0.misc.GL_thetas(ntheta)
    w = ducc0.misc.GL_weights(ntheta, nphi)
    phi = 2 * np.pi * np.arange(nphi) / nphi
    vec = unit_vectors(theta[:, None], phi[None, :]).reshape(-1, 3)
    return SkyPoints(vec, (sky * w[:, None]).ravel())


def simulate_drift_scan(telescope, freq_hz, lsts, sky, pairs=None, dtype=np.complex128, threads=None, out=None):
    """Noise-free visibilities for every sidereal angle in ``lsts`` (radians).

    Parameters
    ----------
    telescope : mmflow.telescope.Telescope
    freq_hz : float
    lsts : array_like, shape (n_time,)
    sky : SkyPoints
    pairs : ndarray (n_bl, 2), optional
        Antenna pairs; defaults to ``telescope.antenna_pairs()``.
    dtype : complex64 or complex128
        Working precision. complex64 forms phases, sincos and the product in float32: a
        phase error of ~6e-8 x 2 pi |x| / lambda rad for an antenna |x| from the origin.
    threads : int, optional
        Time steps are split into this many contiguous blocks run concurrently, each with
        single-threaded BLAS (default :func:`mmflow.threads.n_threads`, or 1 for a small problem,
        :data:`SERIAL_WORK`).
    out : ndarray (n_time, n_bl) complex, optional
        Filled in place and returned (e.g. one source's slice of a stack of sources: no stacked
        copy; at 256 antennas a time chunk of one source is 135 MB in complex128).

    Returns
    -------
    ndarray, shape (n_time, n_bl), complex128 (or ``out``'s dtype), Jy
    """
    pairs = telescope.antenna_pairs() if pairs is None else np.asarray(pairs)
    lsts = np.atleast_1d(np.asarray(lsts, float))
    rdtype = np.float32 if np.dtype(dtype) == np.complex64 else np.float64
    if out is None:
        out = np.empty((len(lsts), len(pairs)), np.complex128)
    elif out.shape != (len(lsts), len(pairs)) or out.dtype.kind != "c":
        raise ValueError(
            f"simulate_drift_scan: out is {out.dtype} {out.shape}, not complex ({len(lsts)}, {len(pairs)})"
        )
    if threads is None and len(lsts) * max(1, len(sky.flux_jy)) * len(telescope.layout.enu) ** 2 < SERIAL_WORK:
        threads = 1  # a few points (a calibration model): starting threads costs more than the work
    threads = max(1, min(n_threads() if threads is None else threads, len(lsts)))
    block = (_simulate_pairs if few_pairs(pairs, len(telescope.layout.enu)) else
             _simulate_points if len(sky.flux_jy) <= FEW_POINTS else _simulate_block)
    if threads == 1:  # each time step is computed alone: the same values as in any split over threads
        block(telescope, freq_hz, lsts, sky, pairs, rdtype, out)
        return out
    bounds = np.linspace(0, len(lsts), threads + 1).astype(int)
    blocks = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
    with single_threaded_blas(threads > 1), ThreadPoolExecutor(max_workers=threads) as pool:
        list(pool.map(lambda sl: block(telescope, freq_hz, lsts[sl], sky, pairs, rdtype, out[sl]), blocks))
    return out


def few_pairs(pairs, n_ant):
    """Whether ``pairs`` are computed pair-wise (:func:`_simulate_pairs`) rather than as every pair of
    the array (:func:`_simulate_block`): when ``8 |A| |B| < n_ant^2``, ``A`` and ``B`` the antennas
    at the baselines' first and second ends (measured on this VM for one point source at 256
    antennas: a 256-baseline chunk 5-7x faster pair-wise, 8,192 baselines of 33 first antennas,
    ``|A| |B| ~ n^2 / 8``, 1.3x slower)."""
    return 8 * len(np.unique(pairs[:, 0])) * len(np.unique(pairs[:, 1])) < n_ant ** 2


def _simulate_pairs(telescope, freq_hz, lsts, sky, pairs, rdtype, out):
    """Fill ``out[t]`` for ``pairs`` only: ``Q = conj(Z_A) W Z_B^T`` between the antennas ``A`` at the
    baselines' first ends and ``B`` at their second, ``V_ij = Q[i, j]``.

    The rank-k product of :func:`_simulate_block` forms every antenna pair (``4 n^2`` per point and
    time step); a chunk of baselines of a large array (a corner turn's: one or two first antennas,
    every second one) needs ``|A| |B| << n^2`` of them. Each time step's product is its own (the same
    values in any split over time)."""
    x = _antenna_phases(telescope, freq_hz, rdtype)
    a, ea = np.unique(pairs[:, 0], return_inverse=True)
    b, eb = np.unique(pairs[:, 1], return_inverse=True)
    ctype = complex_dtype(rdtype).type
    for t0 in range(0, len(lsts), TIME_BLOCK):
        phis = lsts[t0:t0 + TIME_BLOCK]
        r = np.stack([sky.vectors @ enu_to_equatorial_matrix(telescope.lat_rad, phi) for phi in phis])  # ENU
        up = r[..., 2] > 0
        w = np.zeros(up.shape)
        w[up] = telescope.beam.power_enu(r[up], freq_hz) * np.broadcast_to(sky.flux_jy, up.shape)[up]
        q = np.zeros((len(phis), len(a), len(b)), ctype)
        for s0 in range(0, r.shape[1], PIXEL_BLOCK):
            rs = r[:, s0:s0 + PIXEL_BLOCK].astype(rdtype)
            za = _expi(-(rs @ x[a].T), ctype)  # conj(z), (time, point, antenna)
            za *= w[:, s0:s0 + PIXEL_BLOCK, None].astype(rdtype)
            q += np.matmul(za.transpose(0, 2, 1), _expi(rs @ x[b].T, ctype))
        out[t0:t0 + TIME_BLOCK] = q[:, ea.ravel(), eb.ravel()]


def _antenna_phases(telescope, freq_hz, rdtype):
    """Antenna positions in radians of phase per unit direction, ``2 pi x / lambda`` (n_ant, 3): the phase
    ``2 pi x.r`` is formed directly in the working precision (sin/cos reduce large arguments exactly,
    so reducing in turns first would not make a float32 phase any more accurate)."""
    return (2 * np.pi * telescope.layout.enu / (SPEED_OF_LIGHT / freq_hz)).astype(rdtype)


def _expi(phase, ctype):
    """``exp(i phase)`` from one cosine and one sine (``np.exp`` of a complex argument also forms ``exp(0)``)."""
    z = np.empty(phase.shape, ctype)
    np.cos(phase, out=z.real)
    np.sin(phase, out=z.imag)
    return z


def _simulate_block(telescope, freq_hz, lsts, sky, pairs, rdtype, out):
    """Fill ``out[t]`` for the sidereal angles ``lsts``; buffers are reused across time steps."""
    x = _antenna_phases(telescope, freq_hz, rdtype)
    n = len(x)
    syrk = blas.ssyrk if rdtype == np.float32 else blas.dsyrk
    # Q is upper-triangular from syrk: read Q[i, j] as Q[min, max]
    i, j = pairs[:, 0], pairs[:, 1]
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    sign = np.where(i <= j, 1.0, -1.0)  # Im V_ij = Q_CS[i, j] - Q_CS[j, i] = sign * (Q[lo, n+hi] - Q[hi, n+lo])
    cols = max(1, min(PIXEL_BLOCK, len(sky.flux_jy)))  # an empty sky: no pixel blocks, zero visibilities
    phase_buf = np.empty((n, cols), rdtype)
    p_buf = np.empty((2 * n, cols), rdtype)
    for t, phi in enumerate(lsts):
        rot = enu_to_equatorial_matrix(telescope.lat_rad, phi)  # r_enu = M^T r_eq
        up = sky.vectors @ rot[:, 2] > 0
        r_up = sky.vectors[up] @ rot
        w_up = telescope.beam.power_enu(r_up, freq_hz) * sky.flux_jy[up]
        if np.any(w_up < 0):
            q = np.zeros((2 * n, 2 * n))
            for s0 in range(0, len(r_up), cols):
                p = _phasors(x, r_up[s0:s0 + cols], phase_buf, p_buf)
                q += (p * w_up[s0:s0 + cols].astype(rdtype)) @ p.T
        else:
            # real form of V = conj(Z) W Z^T with Z = C + i S: Q = [C; S] W [C; S]^T, accumulated
            # over cache-sized pixel blocks (upper triangle; p.T is Fortran-ordered: no copy)
            q = np.zeros((2 * n, 2 * n), rdtype, order="F")
            for s0 in range(0, len(r_up), cols):
                p = _phasors(x, r_up[s0:s0 + cols], phase_buf, p_buf)
                p *= np.sqrt(w_up[s0:s0 + cols]).astype(rdtype)
                q = syrk(1.0, p.T, beta=1.0, c=q, trans=1, lower=0, overwrite_c=1)
        out[t].real = q[lo, hi] + q[n + lo, n + hi]
        out[t].imag = sign * (q[lo, n + hi] - q[hi, n + lo])


def _simulate_points(telescope, freq_hz, lsts, sky, pairs, rdtype, out):
    """Fill ``out[t]`` as :func:`_simulate_block` does, summing over the few points per baseline,
    ``V_ij = sum_p w_p conj(z_ip) z_jp``, without the rank-k product's antenna-pair matrix (one time
    step at a time: the gathers of one step's phasors by antenna are faster than of several)."""
    x = _antenna_phases(telescope, freq_hz, rdtype)
    ctype = complex_dtype(rdtype).type
    i, j = pairs[:, 0], pairs[:, 1]
    for t, phi in enumerate(lsts):
        rot = enu_to_equatorial_matrix(telescope.lat_rad, phi)  # r_enu = M^T r_eq
        up = sky.vectors @ rot[:, 2] > 0
        r_up = sky.vectors[up] @ rot
        w_up = (telescope.beam.power_enu(r_up, freq_hz) * sky.flux_jy[up]).astype(rdtype)
        z = _expi(x @ r_up.T.astype(rdtype), ctype)  # (n_ant, n_up)
        v = np.zeros(len(pairs), ctype)
        for k in range(len(w_up)):
            zk = z[:, k]
            v += np.conj(zk[i]) * (w_up[k] * zk[j])
        out[t] = v


def _phasors(x, r, phase_buf, p_buf):
    """``[cos(x.r); sin(x.r)]`` (2 n_ant, n_dir) into reused buffers (views of their first columns)."""
    n, k = len(x), len(r)
    phase = phase_buf[:, :k]
    np.matmul(x, r.T.astype(x.dtype, copy=False), out=phase)
    p = p_buf[:, :k]
    np.cos(phase, out=p[:n])
    np.sin(phase, out=p[n:])
    return p


def thermal_noise(vis, autos_i, autos_j, bandwidth_hz, integration_s, rng, is_auto=None):
    """Radiometer-equation noise: ``sigma_ij = sqrt(V_ii V_jj / (dnu tau))``.

    Cross-correlations get complex noise, ``sigma / sqrt(2)`` per component; the
    autocorrelations (``is_auto``, broadcast against ``vis``) real noise of standard deviation
    ``sigma_ii = V_ii / sqrt(dnu tau)``: an autocorrelation is real. ``autos_i``/``autos_j`` are
    the autocorrelation powers (Jy) of each baseline's antennas, broadcast against ``vis``.
    Returns the noise array and ``sigma``.
    """
    sigma = np.sqrt(np.abs(autos_i * autos_j) / (bandwidth_hz * integration_s))
    re, im = rng.normal(size=vis.shape), rng.normal(size=vis.shape)
    noise = sigma / np.sqrt(2) * (re + 1j * im)
    if is_auto is not None:
        noise = np.where(np.broadcast_to(is_auto, noise.shape), sigma * re + 0j, noise)
    return noise, sigma


def auto_columns(pairs):
    """For radiometer noise: which baselines are autocorrelations, and for each baseline the columns of
    its two antennas' autocorrelations among them (refused when there are none)."""
    is_auto = pairs[:, 0] == pairs[:, 1]
    if not is_auto.any():
        raise InputError("workflow", "sky.noise", "thermal noise needs autocorrelations",
                         "set telescope.include_autos=true or sky.noise=false")
    col = {int(p[0]): c for c, p in enumerate(pairs[is_auto])}
    return is_auto, [col[int(p)] for p in pairs[:, 0]], [col[int(p)] for p in pairs[:, 1]]
