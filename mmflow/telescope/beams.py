"""Primary beams: one interface for analytic, Zernike (paper section 3.3) and pyuvdata beams.

Every beam is a Stokes-I *power* response ``A(az, za; nu)``, dimensionless, zero below
the horizon (``za > pi/2``). Azimuth is measured from north through east (mmflow's
convention); pyuvdata's azimuth (from east through north) is converted here.
"""
from __future__ import annotations

from math import factorial

import numpy as np

from mmflow.errors import InputError


class BeamModel:
    """What scalar power beams (:class:`Beam`) and E-field beams
    (:class:`mmflow.telescope.jones.JonesBeam`) share: the frequency check, the description and
    evaluation above the horizon only."""

    name = "beam"
    freq_range = None  # (lowest, highest) Hz the model covers (a beam file's channels); None: any
    source = "beam"  # what an error names (a beam file's path)

    def check_frequency(self, freq_hz):
        """Raise :class:`InputError` when ``freq_hz`` is outside the beam model's ``freq_range``."""
        if self.freq_range and not (self.freq_range[0] <= freq_hz <= self.freq_range[1]):
            raise InputError(self.source, "freq_array", f"{freq_hz / 1e6:.3f} MHz outside the beam's "
                             f"{self.freq_range[0] / 1e6:.3f}-{self.freq_range[1] / 1e6:.3f} MHz",
                             "use a beam file that covers the observed channels")

    def describe(self):
        """A JSON-able description stored with every output."""
        return {"type": self.name}

    def _above_horizon(self, response, az, za, freq_hz, lead=(), dtype=float):
        """``response(az, za, freq)`` where ``za < pi/2``, zero elsewhere: shape ``lead + az.shape``
        (``az``, ``za`` broadcast; the frequency checked first)."""
        self.check_frequency(freq_hz)
        az, za = np.broadcast_arrays(np.asarray(az, float), np.asarray(za, float))
        out = np.zeros(lead + az.shape, dtype)
        up = za < np.pi / 2
        if np.any(up):
            out[..., up] = response(az[up], za[up], float(freq_hz))
        return out


class Beam(BeamModel):
    """Base class. Subclasses implement :meth:`_response` for ``za <= pi/2``.

    Attributes
    ----------
    lmax_hint : int
        Angular band limit of the beam pattern used to size quadrature grids and the
        per-baseline lmax (``lmax_b = 1.1 * 2 pi |b| / lambda + lmax_hint``).
    """

    lmax_hint = 24
    name = "beam"

    def power(self, az, za, freq_hz):
        """Power response at azimuth ``az`` and zenith angle ``za`` (radians), zero below horizon."""
        return self._above_horizon(self._response, az, za, freq_hz)

    def power_enu(self, enu, freq_hz):
        """Power response for ENU unit vectors (last axis east, north, up)."""
        enu = np.asarray(enu)
        az = np.arctan2(enu[..., 0], enu[..., 1])
        za = np.arccos(np.clip(enu[..., 2], -1, 1))
        return self.power(az, za, freq_hz)

    def _response(self, az, za, freq_hz):
        raise NotImplementedError


class SinElevationBeam(Beam):
    """``A = sin(elevation)^alpha = cos(za)^alpha`` (frequency independent).

    ``alpha ~ 1.5`` mimics a dipole over a ground screen. The band limit is about
    ``alpha`` plus the horizon cut-off, hence ``lmax_hint = max(16, 4 alpha)``.
    """

    name = "sin_elevation"

    def __init__(self, alpha=1.5):
        if alpha <= 0:
            raise InputError("beam", "alpha", f"alpha={alpha} must be positive", "use e.g. alpha: 1.5")
        self.alpha = float(alpha)
        self.lmax_hint = int(max(16, 4 * alpha))

    def _response(self, az, za, freq_hz):
        return np.cos(za) ** self.alpha

    def power_enu(self, enu, freq_hz):
        """``A = u^alpha`` for ENU unit vectors, ``u`` their up component clipped to [0, 1] (``cos za``;
        0 below the horizon): no angles formed (the simulator evaluates it for every sky point and
        integration, where the angles cost ~20 % of its time)."""
        self.check_frequency(freq_hz)
        return np.clip(np.asarray(enu, float)[..., 2], 0.0, 1.0) ** self.alpha


class GaussianBeam(Beam):
    """``A = exp(-za^2 / (2 sigma^2))`` with ``sigma = fwhm / sqrt(8 ln 2)`` scaled as ``nu_ref/nu``."""

    name = "gaussian"

    def __init__(self, fwhm_deg=60.0, ref_freq_hz=None):
        self.fwhm_deg = float(fwhm_deg)
        self.ref_freq_hz = ref_freq_hz
        self.lmax_hint = int(np.clip(4 * 180.0 / self.fwhm_deg, 16, 256))

    def sigma(self, freq_hz):
        s = np.deg2rad(self.fwhm_deg) / np.sqrt(8 * np.log(2))
        return s * (self.ref_freq_hz / freq_hz if self.ref_freq_hz else 1.0)

    def _response(self, az, za, freq_hz):
        return np.exp(-0.5 * (za / self.sigma(freq_hz)) ** 2)

    def describe(self):
        return {"type": self.name, "fwhm_deg": self.fwhm_deg, "ref_freq_hz": self.ref_freq_hz}


#: The (n, m) Zernike terms of the paper's OVRO-LWA beam fits (section 3.3).
ZERNIKE_TERMS = ((0, 0), (2, 0), (4, 0), (4, 4), (6, 0), (6, 4), (8, 0), (8, 4), (8, 8))


def zernike_radial(n, m, rho):
    """Zernike radial polynomial ``R_n^m(rho) = sum_k (-1)^k (n-k)! / (k! ((n+m)/2-k)! ((n-m)/2-k)!) rho^(n-2k)``."""
    rho = np.asarray(rho, float)
    out = np.zeros_like(rho)
    for k in range((n - m) // 2 + 1):
        c = (-1) ** k * factorial(n - k) / (factorial(k) * factorial((n + m) // 2 - k)
                                            * factorial((n - m) // 2 - k))
        out += c * rho ** (n - 2 * k)
    return out


def zernike_basis(az, za):
    """The paper's nine symmetric Zernike terms ``R_n^m(rho) cos(m az)``, ``rho = sin(za)``.

    Returns shape ``(9,) + az.shape``. With azimuth from north, ``cos(4 az)`` and
    ``cos(8 az)`` keep the N-S / E-W flip and 90-degree rotation symmetries the paper assumes.
    """
    rho = np.sin(za)
    return np.stack([zernike_radial(n, m, rho) * np.cos(m * az) for n, m in ZERNIKE_TERMS])


class ZernikeBeam(Beam):
    """Zernike-polynomial beam (paper section 3.3), unity at zenith, coefficients per frequency.

    Parameters
    ----------
    freqs_hz : array_like, shape (n_freq,)
        Frequencies at which coefficients are given (ascending).
    coeffs : array_like, shape (n_freq, 9)
        Coefficients of :data:`ZERNIKE_TERMS`. They are normalised so that the beam is 1
        at zenith; between frequencies coefficients are interpolated linearly.
    """

    name = "zernike"
    lmax_hint = 40

    def __init__(self, freqs_hz, coeffs):
        self.freqs_hz = np.atleast_1d(np.asarray(freqs_hz, float))
        c = np.atleast_2d(np.asarray(coeffs, float))
        if c.shape != (len(self.freqs_hz), len(ZERNIKE_TERMS)):
            raise InputError("zernike beam", "coeffs", f"shape {c.shape}",
                             f"give ({len(self.freqs_hz)}, 9) coefficients for {ZERNIKE_TERMS}")
        zen = zernike_basis(np.zeros(1), np.zeros(1))[:, 0]
        norm = c @ zen
        if np.any(np.abs(norm) < 1e-12):
            raise InputError("zernike beam", "coeffs", "beam is zero at zenith", "check the coefficients")
        self.coeffs = c / norm[:, None]

    def check_frequency(self, freq_hz):
        lo, hi = self.freqs_hz[0], self.freqs_hz[-1]
        if not (lo * (1 - 1e-9) <= freq_hz <= hi * (1 + 1e-9)):
            raise InputError("zernike beam", "frequency", f"{freq_hz / 1e6:.3f} MHz outside the model's "
                             f"{lo / 1e6:.3f}-{hi / 1e6:.3f} MHz", "give coefficients covering every channel")

    def coefficients(self, freq_hz):
        if len(self.freqs_hz) == 1:
            return self.coeffs[0]
        return np.array([np.interp(freq_hz, self.freqs_hz, self.coeffs[:, i]) for i in range(9)])

    def _response(self, az, za, freq_hz):
        val = np.tensordot(self.coefficients(freq_hz), zernike_basis(az, za), axes=1)
        return np.clip(val, 0.0, None)

    @classmethod
    def fit(cls, beam, freqs_hz, n_grid=60):
        """Least-squares Zernike fit (zenith-normalised) of another beam at ``freqs_hz``."""
        za, az = np.meshgrid(np.linspace(0, np.pi / 2 * 0.999, n_grid), np.linspace(0, 2 * np.pi, 2 * n_grid))
        basis = zernike_basis(az.ravel(), za.ravel()).T
        coeffs = [np.linalg.lstsq(basis, beam.power(az.ravel(), za.ravel(), f), rcond=None)[0] for f in freqs_hz]
        return cls(freqs_hz, coeffs)

    def describe(self):
        return {"type": self.name, "freqs_hz": self.freqs_hz.tolist(), "coeffs": self.coeffs.tolist()}


def read_pyuvdata_beam(beam):
    """``(source, beam)``: ``beam`` itself (a pyuvdata beam object) or the file at the path ``beam``
    read by pyuvdata (refused, naming the file, when it cannot); ``source`` names it in errors."""
    from pyuvdata import UVBeam  # deferred: pyuvdata takes 2-3.5 s to import (docs/performance.md)

    source = beam if isinstance(beam, str) else type(beam).__name__
    if isinstance(beam, str):
        try:
            beam = UVBeam.from_file(beam)
        except Exception as exc:  # pyuvdata raises many types
            raise InputError(source, "beam file", f"pyuvdata cannot read it ({exc})",
                             "give a beamfits / MWA / CST file pyuvdata supports") from exc
    return source, beam


def beam_freq_range(interface):
    """``(lowest, highest)`` Hz of a pyuvdata ``BeamInterface``'s channels (None for an analytic beam)."""
    freqs = getattr(interface.beam, "freq_array", None)
    return None if freqs is None else (float(np.min(freqs)), float(np.max(freqs)))


class PyUVDataBeam(Beam):
    """Any pyuvdata beam (``AnalyticBeam`` objects or ``UVBeam`` files) through ``BeamInterface``.

    The Stokes-I power response is ``A_I = (XX + YY) / 2`` (or the single polarisation present),
    with the beam's own normalisation (a beam file says what zenith is; pyuvdata's power beams,
    e.g. of a short dipole, are ``XX = |J_x|^2 = 1`` there); ``normalize=True`` rescales to 1 at
    zenith. It is the response of visibilities in mmflow's ``avg`` convention,
    ``V_pp = int |J_p|^2 I e^{2 pi i b.r} dOmega`` and ``V_I = (V_xx + V_yy) / 2 = int A_I I ...``:
    data simulated through the same beam by matvis or pyuvsim carry ``V_pp / 2`` (pyuvdata's
    ``pol_convention = "sum"``) and are doubled on ingest (:func:`mmflow.io.polarization.pol_factor`).

    Parameters
    ----------
    beam : pyuvdata.UVBeam, pyuvdata.analytic_beam.AnalyticBeam, or str
        A beam object, or the path of a beamfits/other file pyuvdata reads.
    """

    name = "pyuvdata"

    def __init__(self, beam, normalize=False, lmax_hint=48):
        from pyuvdata import BeamInterface  # deferred: pyuvdata takes 2-3.5 s to import (docs/performance.md)

        self.source, beam = read_pyuvdata_beam(beam)
        self.interface = BeamInterface(beam, beam_type="power")
        self.normalize = normalize
        self.lmax_hint = lmax_hint
        self.freq_range = beam_freq_range(self.interface)

    def _raw(self, az, za, freq_hz):
        az_uvb = (np.pi / 2 - az) % (2 * np.pi)  # pyuvdata: azimuth from east through north
        resp = self.interface.compute_response(az_array=az_uvb, za_array=za,
                                               freq_array=np.array([freq_hz]))
        resp = np.real(resp[0, :, 0, :])  # (npol, npix)
        pols = getattr(self.interface, "polarization_array", None)
        if resp.shape[0] >= 2 and pols is not None and len(pols) >= 2:
            return 0.5 * (resp[0] + resp[1])
        return resp[0]

    def _response(self, az, za, freq_hz):
        val = self._raw(az, za, freq_hz)
        if self.normalize:
            val = val / self._raw(np.zeros(1), np.zeros(1), freq_hz)[0]
        return val

    def describe(self):
        return {"type": self.name, "source": self.source}
