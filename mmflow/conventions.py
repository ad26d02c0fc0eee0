"""The conventions every module shares, in one place.

Sidereal angle
    ``phi`` is the local (apparent) sidereal time in radians. The sky frame is the
    celestial frame *of date* (astropy ``TETE`` at the observation epoch). At ``phi = 0``
    the array's zenith points at RA = 0, Dec = latitude of that frame.

m-mode transform
    ``V_m = (1/N) sum_n V(phi_n) exp(-i m phi_n)`` over N equal sidereal bins, so that
    ``V(phi) = sum_m V_m exp(i m phi)``.

Sky
    Real brightness, ``a_lm`` for ``m >= 0`` with healpy's orthonormal ``Y_lm``;
    ``a_{l,-m} = (-1)^m conj(a_lm)``.

Transfer coefficients
    ``B_lm(b) = int A(r) exp(2 pi i b.r / lambda) Y_lm(r) dOmega`` with ``A`` and ``b``
    expressed in the sky frame at ``phi = 0``. Then ``V_m = sum_l B_lm a_lm`` for
    ``m >= 0``, and ``conj(V_{-m}) = sum_l B_lm(-b) a_lm``: the -m row of baseline (i, j) is
    the +m row of baseline (j, i).

Row layout of an m block
    rows ``0..Nb-1`` are ``V_m`` of baselines ``0..Nb-1``; for ``m > 0`` rows ``Nb..2Nb-1``
    are ``conj(V_{-m})`` of the same baselines. Columns are ``l = m..lmax``.

Sidereal day
    ``SIDEREAL_DAY_S`` = 86164.0905 s of UTC: the sidereal angle advances by ``2 pi`` in it.
    A drift scan's integration ``k`` is at ``phi_k = phi_0 + 2 pi k tau / T_sid`` (:func:`drift_scan_lsts`).

Stokes parameters
    ``imaging.stokes`` is ``[I]`` or the full set :data:`FULL_STOKES` (:func:`is_full_stokes`).
    IAU (1974): Q > 0 for an electric field north-south, angles from north through east, V > 0
    for the field rotating from north through east as the receiver sees it. With the fringe
    above (``V_ij = <E_i E_j*>``, ``exp(+2 pi i b.r / lambda)``, i.e. fields ``Re[A exp(-i w t)]``)
    the coherency on ``(e_N, e_E)`` is ``[[I + Q, U - iV], [U + iV, I - Q]]``
    (:data:`STOKES_COHERENCY`, :func:`stokes_coherency`; derivation in docs/conventions.md).

Units
    Visibilities in Jy; beams are power responses, 1 at zenith; transfer matrices map
    brightness in Jy/sr to Jy (units of sr). Maps are converted to K (default) only by
    :mod:`mmflow.sky.units`.
"""
import numpy as np

SIDEREAL_DAY_S = 86164.0905  # s: one turn of the sidereal angle
TWO_PI = 2 * np.pi  # rad: one turn (of the sidereal angle, of an m-mode phase)
SPEED_OF_LIGHT = 299792458.0  # m/s, exact (SI): every wavelength in mmflow is SPEED_OF_LIGHT / freq_hz
#: the Stokes parameters of full-Stokes imaging, as ``imaging.stokes`` lists them
FULL_STOKES = ("I", "Q", "U", "V")
#: ``sigma_X``: the coherency ``<A A^H>`` on the sky basis ``(e_N, e_E)`` of unit IAU Stokes X, X = I, Q, U, V,
#: for field phasors ``A`` of ``E(t) = Re[A exp(-i w t)]`` (the time dependence that mmflow's fringe
#: ``exp(+2 pi i b.r / lambda)`` with ``V_ij = <E_i E_j*>`` implies). IAU +V (``E`` turning from north
#: through east) is ``A = (1, i)``: ``A_N conj(A_E) = -i``, hence the ``-i`` of ``sigma_V[0, 1]``.
STOKES_COHERENCY = np.array([[[1, 0], [0, 1]], [[1, 0], [0, -1]], [[0, 1], [1, 0]], [[0, -1j], [1j, 0]]], complex)

#: the feeds of the cross hands (``vis.zarr``'s ``cross_pol`` axis) against the parallel hands' axis: cross
#: hand k correlates feed ``CROSS_FEEDS[0][k]`` of antenna i with feed ``CROSS_FEEDS[1][k]`` of antenna j
#: (xy: x of i, y of j; yx: y of i, x of j; likewise rl, lr)
CROSS_FEEDS = ((0, 1), (1, 0))


def complex_dtype(dtype):
    """The complex dtype of a working precision: ``complex64`` for float32 (or complex64), else ``complex128``.

    The one rule for every array whose precision follows a real one (transfer matrices, Grams,
    visibilities in a kernel's working precision); ``.type`` gives numpy's scalar type, ``.name`` the
    string stored in zarr attributes.
    """
    return np.dtype(np.complex64) if np.dtype(dtype) in (np.float32, np.complex64) else np.dtype(np.complex128)


def is_full_stokes(stokes):
    """True when ``stokes`` (``imaging.stokes``) asks for I, Q, U and V."""
    return tuple(stokes) == FULL_STOKES


def stokes_coherency(stokes):
    """The sky's coherency ``S = sum_X X sigma_X`` on ``(e_N, e_E)`` of IAU Stokes ``(..., [I, Q, U, V])``::

        S = <E E^H> = [[I + Q, U - iV],
                       [U + iV, I - Q]]

    in mmflow's ``avg`` normalisation (an unpolarised source of flux I gives ``S = I 1``) and
    fringe convention (:data:`STOKES_COHERENCY`). Returns complex ``(..., 2, 2)``.
    """
    return np.tensordot(np.asarray(stokes, float), STOKES_COHERENCY, axes=([-1], [0]))


def drift_scan_lsts(start_lst_rad, integration_s, index):
    """``phi_k = phi_0 + 2 pi k tau / T_sid (mod 2 pi)`` for integration indices ``k``."""
    k = np.asarray(index, float)
    return (start_lst_rad + 2 * np.pi * k * integration_s / SIDEREAL_DAY_S) % (2 * np.pi)


def drift_scan_times(epoch_jd, integration_s, index, n_total):
    """UTC JD of each integration, centred on ``epoch_jd``: ``t_k = t_0 + (k - n/2) tau``."""
    return epoch_jd + (np.asarray(index, float) - n_total / 2) * integration_s / 86400.0


def enu_to_equatorial_matrix(lat_rad, phi=0.0):
    """Rotation taking ENU components to celestial-of-date (x to RA=0, z to the pole).

    Columns are the east, north and zenith unit vectors expressed in the celestial frame
    when the local sidereal time is ``phi``:

    ``E = (-sin phi, cos phi, 0)``,
    ``N = (-sin lat cos phi, -sin lat sin phi, cos lat)``,
    ``Z = (cos lat cos phi, cos lat sin phi, sin lat)``.

    Returns
    -------
    ndarray, shape (3, 3)
        ``r_eq = M @ r_enu``; its transpose takes celestial vectors to ENU.
    """
    sl, cl = np.sin(lat_rad), np.cos(lat_rad)
    sp, cp = np.sin(phi), np.cos(phi)
    return np.array([[-sp, -sl * cp, cl * cp],
                     [cp, -sl * sp, cl * sp],
                     [0.0, cl, sl]])


def unit_vectors(theta, phi):
    """Cartesian unit vectors of colatitude ``theta`` and longitude ``phi`` (last axis xyz)."""
    st = np.sin(theta)
    return np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), np.cos(theta)), axis=-1)


def radec_to_vec(ra_rad, dec_rad):
    """Unit vectors for right ascension and declination (radians)."""
    return unit_vectors(np.pi / 2 - np.asarray(dec_rad), np.asarray(ra_rad))


def enu_to_azza(enu):
    """Azimuth (from north through east) and zenith angle of ENU unit vectors."""
    enu = np.asarray(enu)
    az = np.arctan2(enu[..., 0], enu[..., 1]) % (2 * np.pi)
    za = np.arccos(np.clip(enu[..., 2], -1.0, 1.0))
    return az, za


def alm_index(lmax, l, m):
    """healpy's index of ``a_lm`` (m-major) for ``mmax = lmax``."""
    return m * (2 * lmax + 1 - m) // 2 + l


def n_alm(lmax):
    """Number of ``a_lm`` with ``0 <= m <= l <= lmax``."""
    return (lmax + 1) * (lmax + 2) // 2


def m_slice(lmax, m):
    """Slice of the healpy alm vector holding ``a_lm`` for ``l = m..lmax``: the one-m block
    :func:`m_block_slice` ``(lmax, m, m + 1)``."""
    return m_block_slice(lmax, m, m + 1)


def m_blocks(mmax, m_block):
    """The m blocks ``[(m0, m1), ...]`` covering ``m = 0..mmax``: ``m0 = 0, b, 2b, ... <= mmax``,
    ``m1 = min(m0 + b, mmax + 1)`` with ``b = m_block`` (the last block may be shorter)."""
    return [(m0, min(mmax + 1, m0 + m_block)) for m0 in range(0, mmax + 1, m_block)]


#: ``imaging.stokes_lmax`` when null: the band limit of Q, U and V (E, B, V harmonics), or ``mmode.lmax`` if
#: lower. 256 is ~0.7 deg (pi / 256): what a day's drift scan at tens of MHz measures of the polarised sky
#: (Faraday rotation depolarises it; the polarised point sources are few and weak), at ~7x the Stokes-I
#: Gram's cost at lmax 1000 instead of 64x; the beam's leakage of I into the cross hands keeps T's band
#: limit. docs/stokes.md, "The band limit of Q, U and V".
STOKES_LMAX_DEFAULT = 256


def stokes_sizes(m, lmax, lmax_p=None):
    """Unknowns of block m: ``(L_m, P_m)``, ``L_m = lmax - m + 1`` harmonics of T and ``P_m =
    max(0, lmax_p - m + 1)`` of each of E, B and V (``lmax_p``: their band limit, default ``lmax``)."""
    lmax_p = lmax if lmax_p is None else min(int(lmax_p), lmax)
    return lmax - m + 1, max(0, lmax_p - m + 1)


def m_block_slice(lmax, m_start, m_stop):
    """Slice of the healpy alm vector holding every ``a_lm`` with ``m_start <= m < m_stop``.

    The layout is m-major, so a block of m is contiguous:
    ``[alm_index(lmax, m_start, m_start), alm_index(lmax, m_stop, m_stop))``, the stop clipped to
    ``n_alm(lmax)`` for ``m_stop > lmax``. Its length is the block's number of ``a_lm``.
    """
    stop = n_alm(lmax) if m_stop > lmax else alm_index(lmax, m_stop, m_stop)
    return slice(alm_index(lmax, m_start, m_start), stop)


def healpy_alm(alm_ml, lmax, mmax=None):
    """An ``(m, l)`` padded alm array (as ``alm.zarr`` stores it) as a healpy-layout vector.

    ``out[alm_index(lmax, l, m)] = alm_ml[m, l]`` for ``0 <= m <= mmax``, ``m <= l <= lmax``;
    coefficients with ``m > mmax`` are zero (healpy's vector always has ``mmax = lmax``).

    Parameters
    ----------
    alm_ml : array_like, shape (M, L)
        ``alm_ml[m, l]``; entries with ``l < m`` are padding and ignored, columns beyond ``lmax``
        dropped.
    lmax : int
        Band limit of the output vector.
    mmax : int, optional
        Largest m copied; default ``min(M - 1, lmax)`` (every row the array has).

    Returns
    -------
    numpy.ndarray, complex128, shape (n_alm(lmax),)
    """
    mmax = min(len(alm_ml) - 1, lmax) if mmax is None else mmax
    out = np.zeros(n_alm(lmax), np.complex128)
    for m in range(mmax + 1):
        out[m_slice(lmax, m)] = alm_ml[m, m:lmax + 1]
    return out


def padded_alm(alm, lmax, n_m=None):
    """A healpy-layout alm vector as the ``(m, l)`` padded array stores keep: the inverse of :func:`healpy_alm`.

    ``out[..., m, l] = alm[..., alm_index(lmax, l, m)]`` for ``m <= min(n_m - 1, lmax)``, ``l >= m``;
    0 elsewhere. Leading axes of ``alm`` are kept: ``(..., n_alm(lmax))`` -> ``(..., n_m, lmax + 1)``
    (default ``n_m = lmax + 1``).
    """
    alm = np.asarray(alm)
    n_m = lmax + 1 if n_m is None else n_m
    out = np.zeros(alm.shape[:-1] + (n_m, lmax + 1), np.complex128)
    for m in range(min(n_m - 1, lmax) + 1):
        out[..., m, m:] = alm[..., m_slice(lmax, m)]
    return out
