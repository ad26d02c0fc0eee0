"""The ``clean`` stage's settings: the ``clean:`` section of a workflow (:class:`CleanConfig`).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes it from here.
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator

from mmflow.workflow.config.base import Section, power_of_two


class CleanConfig(Section):
    """m-mode CLEAN (docs/clean.md): PSF by declination, CLEAN to k x jackknife noise, maps, Table 1.

    Major cycles over m blocks (paper section 2.4); restored, residual, model and noise maps and
    PSF stamps in maps/ (products stage).
    """

    enabled: bool = Field(False, description="Run CLEAN after the solve.")
    gain: float = Field(0.15, gt=0, le=1, description="Loop gain: each component takes this fraction of its peak.")
    peaks_per_cycle: int = Field(256, ge=1, description="Peaks (components) picked per major cycle.")
    min_separation_deg: float = Field(3.0, gt=0, lt=180, description="Least distance between the peaks of one "
                                      "cycle (must exceed the PSF main lobe: at least 180 / lmax degrees).")
    peak_fraction: float = Field(0.1, ge=0, lt=1, description="No component from a peak below this fraction of "
                                 "the cycle's largest (0: the paper's N largest pixels).")
    absolute: bool = Field(True, description="Rank peaks by |residual| (negative components allowed).")
    threshold_sigma: float = Field(3.0, gt=0, description="Stop when the residual peak is below this many "
                                   "jackknife noise sigmas (needs mmode.splits with even and odd, or day<k> "
                                   "splits of data spanning two or more sidereal days).")
    threshold: Optional[float] = Field(None, gt=0, description="Stop below this residual peak instead "
                                       "(threshold_unit); null: threshold_sigma x the jackknife noise.")
    threshold_unit: Literal["K", "Jy/sr"] = Field("K", description="Unit of threshold.")
    rel_threshold: float = Field(0.0, ge=0, lt=1, description="Also stop below this fraction of the first "
                                 "cycle's peak (0: off).")
    max_cycles: int = Field(1000, ge=1, description="Stop after this many major cycles.")
    stall_cycles: int = Field(10, ge=0, description="Stop when the best peak of the last this-many cycles is "
                              "not stall_fraction below the best before them (0: off).")
    stall_fraction: float = Field(0.1, ge=0, lt=1, description="See stall_cycles: 0.1 stops a residual falling "
                                  "by less than ~1 % a cycle (calibration and ionospheric errors that point "
                                  "components cannot describe), where a point source falls by the loop gain "
                                  "(docs/clean.md).")
    psf_dec_step_deg: float = Field(2.0, gt=0, le=30, description="Declination step of the PSF table (the PSF "
                                    "depends only on declination; 0, +45 and +75 are always in it).")
    highpass_lmin: Optional[int] = Field(None, ge=1, description="CLEAN only l above this (cosine ramp of "
                                         "highpass_width below it), leaving the smooth sky out (null: off).")
    highpass_width: int = Field(8, ge=0, description="Width in l of the high-pass ramp.")
    nside: Optional[int] = Field(None, description="HEALPix nside of the residual maps CLEAN picks peaks in "
                                 "(default twice the default for lmax).",
                                 json_schema_extra={"allowed": "a power of two (1, 2, 4, ..., 2^29), or null"})
    keep_factors: bool = Field(True, description="Store the Cholesky factors of G + eps I per m block "
                               "(clean.zarr, the Gram's size) instead of refactorising every cycle.")

    @field_validator("nside")
    @classmethod
    def _nside(cls, v):
        return power_of_two(v)


#: this stage's sections of the workflow schema
SECTIONS = {"clean": CleanConfig}
