"""The ``beam`` section: its type and, per type, the model of its parameters.

One model per beam type of :func:`mmflow.telescope.beam_factory.make_beam`; defaults match the beam
classes (a test checks). :class:`BeamConfig` keeps the user's keys as given and validates them
with these (:func:`mmflow.workflow.config.checks.beam_problems`).
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import ConfigDict, Field, model_validator

from mmflow.telescope.beam_factory import required_params
from mmflow.workflow.config.base import Section, UserPath
from mmflow.workflow.config.errors import BadValue


class SinElevationBeamParams(Section):
    """sin_elevation: A = sin(elevation)^alpha, frequency independent."""

    alpha: float = Field(1.5, gt=0, description="Exponent; 1.5 mimics a dipole over a ground screen.")


class GaussianBeamParams(Section):
    """gaussian: A = exp(-za^2 / (2 sigma^2)), sigma = fwhm / sqrt(8 ln 2) scaled by ref_freq_hz / freq."""

    fwhm_deg: float = Field(60.0, gt=0, le=360, description="Full width at half maximum in zenith angle (degrees).")
    ref_freq_hz: Optional[float] = Field(None, gt=0, description="Frequency at which fwhm_deg holds; "
                                         "null: the same width at every frequency.")


class ZernikeBeamParams(Section):
    """zernike: the paper's nine Zernike terms (section 3.3), 1 at zenith, linear in frequency between fits."""

    freqs_hz: list[float] = Field(..., min_length=1, description="Ascending frequencies (Hz) of the fits; "
                                  "they must cover every observed channel.")
    coeffs: list[list[float]] = Field(..., description="One row of 9 coefficients per frequency, for the terms "
                                      "(n, m) = (0,0) (2,0) (4,0) (4,4) (6,0) (6,4) (8,0) (8,4) (8,8).")

    @model_validator(mode="after")
    def _shape(self):
        f = self.freqs_hz
        if any(x <= 0 for x in f) or any(b <= a for a, b in zip(f, f[1:])):
            raise BadValue("freqs_hz must be positive and ascending", "list the fit frequencies in Hz, lowest first")
        if len(self.coeffs) != len(f) or any(len(row) != 9 for row in self.coeffs):
            raise BadValue(f"coeffs has rows of {[len(r) for r in self.coeffs]} coefficients for {len(f)} "
                           "frequencies, not 9 per frequency",
                           "give one row of 9 coefficients per frequency in freqs_hz")
        return self


class ShortDipoleBeamParams(Section):
    """short_dipole: crossed short dipoles, x east, y north (E-field beam: full Stokes; Stokes-I power 1 - sin^2(za)/2).

    The power beam ``(|J_x|^2 + |J_y|^2) / 2`` is ``1 - sin^2(za) / 2`` times ``cos(za)^(2 horizon_taper)``.
    """

    horizon_taper: float = Field(0.0, ge=0, description="Each feed's response times cos(za)^horizon_taper (0: "
                                 "the bare dipole, pyuvdata's ShortDipoleBeam; a taper, e.g. 3, vanishes at the "
                                 "horizon like a dipole over a ground screen, which small lmax needs: docs/stokes.md).")
    lmax_hint: int = Field(24, ge=1, description="Angular band limit of the beam pattern.")


PYUVDATA_ANALYTIC = ("AiryBeam", "GaussianBeam", "ShortDipoleBeam", "UniformBeam")


class PyUVDataBeamParams(Section):
    """pyuvdata: a beam file pyuvdata reads, or one of pyuvdata's analytic beams (give file or class)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, populate_by_name=True)
    file: Optional[UserPath] = Field(None, description="beamfits / MWA / CST file (power or E-field beam).")
    class_: Optional[Literal[PYUVDATA_ANALYTIC]] = Field(None, alias="class",
                                                         description="pyuvdata.analytic_beam class, instead of file.")
    params: dict = Field(default_factory=dict, description="Arguments of that class (e.g. {diameter: 14.0}); "
                         "{} for a class whose signature requires none (ShortDipoleBeam, UniformBeam).")
    normalize: bool = Field(False, description="Rescale to 1 at zenith (default: the beam's own normalisation).")
    lmax_hint: int = Field(48, ge=1, description="Angular band limit of the beam pattern.")

    @model_validator(mode="after")
    def _one_source(self):
        if (self.file is None) == (self.class_ is None):
            raise BadValue("give exactly one of 'file' and 'class'",
                           "beam={type: pyuvdata, file: beam.fits} or beam={type: pyuvdata, class: AiryBeam, "
                           "params: {diameter: 14.0}}")
        missing = [] if self.file is not None else required_params(self.class_, self.params)
        if missing:
            raise BadValue(f"pyuvdata's {self.class_} needs {', '.join(missing)} in 'params'",
                           "e.g. params: {" + ", ".join(f"{n}: ..." for n in missing) + "} (pyuvdata.analytic_beam."
                           f"{self.class_}'s arguments)")
        return self


BEAM_PARAMS = {"sin_elevation": SinElevationBeamParams, "gaussian": GaussianBeamParams,
               "zernike": ZernikeBeamParams, "short_dipole": ShortDipoleBeamParams, "pyuvdata": PyUVDataBeamParams}


class BeamConfig(Section):
    """Primary beam (Stokes-I power, 1 at zenith). The other keys are the parameters of the chosen type."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)
    type: Literal["sin_elevation", "gaussian", "zernike", "short_dipole", "pyuvdata"] = Field(
        "sin_elevation", description="Beam model; its parameters are listed below.")

    def params(self):
        """The beam parameters (the keys other than ``type``) as given."""
        return dict(self.model_extra or {})
