"""Point and Gaussian-component sources with published spectra.

Spectra
-------
* Baars et al. (1977, A&A 61, 99): ``log10 S[Jy] = a + b log10 nu + c log10(nu)^2`` (nu in MHz)
  for Cyg A, Cas A (epoch 1965.0) and Vir A, Tau A.
* Cas A secular decrease 0.77 %/yr (Helmboldt & Kassim 2009), applied from 1965.0.
* Scaife & Heald (2012, MNRAS 423, L30): ``S = A0 prod_i 10^(A_i log10(nu/150 MHz)^i)``.
* Perley & Butler (2017, ApJS 230, 7): ``log10 S = sum_i a_i log10(nu/GHz)^i``; valid above
  ~50 MHz (the reference paper finds them unreliable below), used for Her A, Hya A, 3C 123,
  3C 353.

Positions are J2000 (ICRS) from NED; they are rotated into the frame of date by
:func:`mmflow.sky.frames.rotation_matrix`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mmflow.conventions import radec_to_vec
from mmflow.errors import InputError


def epoch_year(epoch_jd):
    """Julian year of a UTC Julian date (2000.0 at J2000): the ``epoch_year`` of the flux models."""
    return 2000.0 + (float(epoch_jd) - 2451545.0) / 365.25


def _hms(h, m, s):
    return 15.0 * (h + m / 60 + s / 3600)


def _dms(sign, d, m, s):
    return sign * (d + m / 60 + s / 3600)


@dataclass
class Spectrum:
    """A published spectrum ``S(nu)`` in Jy.

    kind: ``baars`` (coefficients a, b, c in log10 MHz), ``sh12`` (A0, A1..), ``pb17``
    (a0, a1, .. in log10 GHz) or ``power_law`` (S0 at nu0 with index alpha).
    """

    kind: str
    coeffs: tuple
    reference: str = ""
    secular_percent_per_year: float = 0.0
    secular_epoch_year: float = 1965.0

    def flux(self, freq_hz, epoch_year=None):
        nu = np.asarray(freq_hz, float)
        c = self.coeffs
        if self.kind == "baars":
            x = np.log10(nu / 1e6)
            s = 10 ** (c[0] + c[1] * x + (c[2] if len(c) > 2 else 0.0) * x**2)
        elif self.kind == "sh12":
            x = np.log10(nu / 150e6)
            s = c[0] * 10 ** sum(ci * x ** (i + 1) for i, ci in enumerate(c[1:]))
        elif self.kind == "pb17":
            x = np.log10(nu / 1e9)
            s = 10 ** sum(ci * x**i for i, ci in enumerate(c))
        elif self.kind == "power_law":
            s = c[0] * (nu / c[1]) ** c[2]
        else:
            raise InputError("spectrum", "kind", f"unknown spectrum kind '{self.kind}'",
                             "use baars, sh12, pb17 or power_law")
        if self.secular_percent_per_year and epoch_year is not None:
            s = s * (1 - self.secular_percent_per_year / 100) ** (epoch_year - self.secular_epoch_year)
        return s


@dataclass
class Source:
    """A compact source: a point, or a sum of elliptical Gaussian components.

    Attributes
    ----------
    name : str
    ra_deg, dec_deg : float
        ICRS (J2000) position of the flux-weighted centre.
    spectrum : Spectrum
    components : list of dict
        Gaussian components ``{"dra_arcmin", "ddec_arcmin", "fraction", "fwhm_major_arcmin",
        "fwhm_minor_arcmin", "pa_deg"}``; empty for a point source.
    """

    name: str
    ra_deg: float
    dec_deg: float
    spectrum: Spectrum
    components: list = field(default_factory=list)

    def flux(self, freq_hz, epoch_year=None):
        return self.spectrum.flux(freq_hz, epoch_year)

    def vector_icrs(self):
        return radec_to_vec(np.deg2rad(self.ra_deg), np.deg2rad(self.dec_deg))

    def points(self, freq_hz, epoch_year=None, n_sigma=None, n_grid=None, n_hermite=12):
        """Directions (ICRS unit vectors) and fluxes (Jy) representing the source.

        A point source is one direction. Each elliptical Gaussian component is sampled on an
        ``n x n`` product grid in its own (major, minor) frame: by default the nodes and weights
        of ``n_hermite``-point Gauss-Hermite quadrature (probabilists'), so that
        ``sum_k w_k exp(i k x_k) = exp(-k^2 sigma^2 / 2)`` to < 5e-9 for ``k sigma <= 2``
        (``2 pi |b| sigma / lambda``; Cas A's widest component at 1.5 km and 73 MHz is 1.4) and
        < 3e-5 at 3; with ``n_sigma`` and ``n_grid`` a uniform grid out to ``n_sigma`` standard
        deviations weighted by the Gaussian (the older sampling: ~7e-4 error at ``k sigma ~ 1``
        for 3 sigma and 9 points, ~2e-7 for 5 sigma and 21). Weights are normalised to the
        component's share of the flux: exact in total flux and centroid. Offsets are placed on
        the tangent plane at the component's centre (``dra_arcmin`` east, ``ddec_arcmin``
        north of the source's position).
        """
        total = float(self.flux(freq_hz, epoch_year))
        if not self.components:
            return self.vector_icrs()[None], np.array([total])
        if n_sigma is None and n_grid is None:
            u, w1 = np.polynomial.hermite_e.hermegauss(n_hermite)
        else:
            u = np.linspace(-(n_sigma or 3.0), n_sigma or 3.0, n_grid or 9)
            w1 = np.exp(-0.5 * u**2)
        gu, gv = np.meshgrid(u, u)
        w = np.outer(w1, w1).ravel()
        w /= w.sum()
        vecs, fluxes = [], []
        fwhm = np.sqrt(8 * np.log(2))
        for comp in self.components:
            ra0 = np.deg2rad(self.ra_deg) + np.deg2rad(comp.get("dra_arcmin", 0.0) / 60) / np.cos(
                np.deg2rad(self.dec_deg)
            )
            dec0 = np.deg2rad(self.dec_deg + comp.get("ddec_arcmin", 0.0) / 60)
            smaj = np.deg2rad(comp["fwhm_major_arcmin"] / 60) / fwhm
            smin = np.deg2rad(comp.get("fwhm_minor_arcmin", comp["fwhm_major_arcmin"]) / 60) / fwhm
            pa = np.deg2rad(comp.get("pa_deg", 0.0))  # east of north
            # offsets (east, north) on the tangent plane
            east = (gu * smaj * np.sin(pa) + gv * smin * np.cos(pa)).ravel()
            north = (gu * smaj * np.cos(pa) - gv * smin * np.sin(pa)).ravel()
            c0 = radec_to_vec(ra0, dec0)
            e_hat = np.array([-np.sin(ra0), np.cos(ra0), 0.0])
            n_hat = np.cross(c0, e_hat)
            v = c0[None] + east[:, None] * e_hat[None] + north[:, None] * n_hat[None]
            vecs.append(v / np.linalg.norm(v, axis=1)[:, None])
            fluxes.append(total * comp.get("fraction", 1.0) * w)
        return np.concatenate(vecs), np.concatenate(fluxes)


CATALOG = {
    "Cyg A": Source("Cyg A", _hms(19, 59, 28.357), _dms(1, 40, 44, 2.10),
                    Spectrum("baars", (4.695, 0.085, -0.178), "Baars et al. 1977")),
    "Cas A": Source("Cas A", _hms(23, 23, 24.0), _dms(1, 58, 48, 54.0),
                    Spectrum("baars", (5.625, -0.634, -0.023), "Baars et al. 1977 (1965.0), "
                             "0.77%/yr secular decrease (Helmboldt & Kassim 2009)", 0.77, 1965.0)),
    "Vir A": Source("Vir A", _hms(12, 30, 49.423), _dms(1, 12, 23, 28.04),
                    Spectrum("baars", (5.023, -0.856, 0.0), "Baars et al. 1977")),
    "Tau A": Source("Tau A", _hms(5, 34, 31.94), _dms(1, 22, 0, 52.2),
                    Spectrum("baars", (3.915, -0.299, 0.0), "Baars et al. 1977")),
    "Her A": Source("Her A", _hms(16, 51, 8.15), _dms(1, 4, 59, 33.3),
                    Spectrum("pb17", (1.8298, -1.0247, -0.0951), "Perley & Butler 2017")),
    "Hya A": Source("Hya A", _hms(9, 18, 5.651), _dms(-1, 12, 5, 43.99),
                    Spectrum("pb17", (1.7795, -0.9176, -0.0843, -0.0139, 0.0295), "Perley & Butler 2017")),
    "3C 123": Source("3C 123", _hms(4, 37, 4.375), _dms(1, 29, 40, 13.82),
                     Spectrum("pb17", (1.8017, -0.7884, -0.1035, -0.0248, 0.0090), "Perley & Butler 2017")),
    "3C 353": Source("3C 353", _hms(17, 20, 28.147), _dms(-1, 0, 58, 46.8),
                     Spectrum("pb17", (1.8627, -0.6938, -0.0998, -0.0732), "Perley & Butler 2017")),
    "3C 48": Source("3C 48", _hms(1, 37, 41.30), _dms(1, 33, 9, 35.1),
                    Spectrum("sh12", (64.768, -0.387, -0.420, 0.181), "Scaife & Heald 2012")),
    "3C 147": Source("3C 147", _hms(5, 42, 36.14), _dms(1, 49, 51, 7.2),
                     Spectrum("sh12", (66.738, -0.022, -1.012, 0.549), "Scaife & Heald 2012")),
    "3C 196": Source("3C 196", _hms(8, 13, 36.03), _dms(1, 48, 13, 2.6),
                     Spectrum("sh12", (83.084, -0.699, -0.110), "Scaife & Heald 2012")),
    "3C 286": Source("3C 286", _hms(13, 31, 8.29), _dms(1, 30, 30, 33.0),
                     Spectrum("sh12", (27.477, -0.158, 0.032, -0.180), "Scaife & Heald 2012")),
    "3C 295": Source("3C 295", _hms(14, 11, 20.52), _dms(1, 52, 12, 9.9),
                     Spectrum("sh12", (97.763, -0.582, -0.298, 0.583, -0.363), "Scaife & Heald 2012")),
    "3C 380": Source("3C 380", _hms(18, 29, 31.78), _dms(1, 48, 44, 46.2),
                     Spectrum("sh12", (77.352, -0.767), "Scaife & Heald 2012")),
}

#: The eight bright sources the reference paper removes before imaging (section 3.5).
PAPER_REMOVED = ("Cyg A", "Cas A", "Vir A", "Tau A", "Her A", "Hya A", "3C 123", "3C 353")
#: The Scaife & Heald (2012) flux calibrators.
SH12_CALIBRATORS = ("3C 48", "3C 147", "3C 196", "3C 286", "3C 295", "3C 380")


def _ring(r_arcmin, pa_deg, fraction, fwhm_major, fwhm_minor, axis_pa_deg):
    """A component ``r_arcmin`` from the centre at position angle ``pa_deg`` (east of north)."""
    pa = np.deg2rad(pa_deg)
    return {"dra_arcmin": r_arcmin * np.sin(pa), "ddec_arcmin": r_arcmin * np.cos(pa), "fraction": fraction,
            "fwhm_major_arcmin": fwhm_major, "fwhm_minor_arcmin": fwhm_minor, "pa_deg": axis_pa_deg}


#: Resolved models (Gaussian components, offsets about the catalogued position) of the two
#: sources the OVRO-LWA marginally resolves (the reference paper, section 3.5: largest angular
#: scales ~2' and ~8'). APPROXIMATIONS for simulation, not fits:
#:
#: * Cyg A: the two lobes, 2.0' apart along the radio axis at PA 110 deg (Carilli & Barthel
#:   1996, A&ARv 7, 1: hotspots ~127" apart, axis PA ~105-110 deg), the western lobe a little
#:   brighter at low frequency (0.55 / 0.45; Lazio et al. 2006 at 74 MHz show comparable lobes),
#:   each 0.6' x 0.35' along the axis;
#: * Cas A: the ~5' shell (e.g. Kassim et al. 1995 at 74 MHz; the shell's outer radius ~2.5')
#:   as three 2.5' x 1.6' components on a ring of radius ~1.2-1.6', tangential to it, the
#:   northern one the brightest (0.4 / 0.3 / 0.3).
#:
#: Both are placed so that the flux-weighted centroid is the catalogued position exactly
#: (``sum_c fraction_c offset_c = 0``), which the point models assume.
RESOLVED_COMPONENTS = {
    "Cyg A": [_ring(0.9, 290.0, 0.55, 0.6, 0.35, 110.0), _ring(1.1, 110.0, 0.45, 0.6, 0.35, 110.0)],
    "Cas A": [_ring(1.2, 0.0, 0.4, 2.5, 1.6, 90.0), _ring(1.6, 120.0, 0.3, 2.5, 1.6, 30.0),
              _ring(1.6, 240.0, 0.3, 2.5, 1.6, 150.0)],
}


def resolved(source):
    """``source`` with its resolved components (:data:`RESOLVED_COMPONENTS`), or as it is (a point)
    if it has none. The catalogue itself stays point sources: only the simulator's ``sky.resolved``
    uses these."""
    comps = RESOLVED_COMPONENTS.get(source.name)
    if not comps or source.components:
        return source
    return Source(source.name, source.ra_deg, source.dec_deg, source.spectrum, [dict(c) for c in comps])


def get_sources(names):
    """Look up catalogue sources by name (``"Cyg A"``, ``"3C 286"``, ...); a :class:`Source` is
    passed through as it is (a resolved or fitted model)."""
    out = []
    for n in names:
        if isinstance(n, Source):
            out.append(n)
            continue
        if n not in CATALOG:
            raise InputError("sky.sources", "name", f"unknown source '{n}'", f"use one of {sorted(CATALOG)}")
        out.append(CATALOG[n])
    return out


def point_source(name, ra_deg, dec_deg, flux_jy, ref_freq_hz=74e6, alpha=-0.7):
    """A power-law point source ``S = flux_jy (nu / ref)^alpha``."""
    return Source(name, ra_deg, dec_deg, Spectrum("power_law", (flux_jy, ref_freq_hz, alpha)))
