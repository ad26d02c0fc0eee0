"""The ``solve`` stage's settings (:data:`SECTIONS`): the ``imaging:`` section of a workflow
(:class:`ImagingConfig`; the normal, solve and stokes stages read it).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes them from here, in the
pipeline's order.
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator

from mmflow.workflow.config.base import Section
from mmflow.workflow.config.errors import BadValue


class ImagingConfig(Section):
    """The regularised solve for a_lm."""

    method: Literal["tikhonov", "min_variance", "moore_penrose", "prior", "smoothness"] = Field(
        "tikhonov", description="Solver (prior needs prior_map).")
    eps: float = Field(0.01, gt=0, description="Regularisation parameter (paper: 0.01).")
    zero_monopole: bool = Field(True, description="Set a_00 to zero (the array does not measure it).")
    filter_m0: bool = Field(True, description="Drop m = 0 (confused with ground pick-up and cross-talk).")
    filter_m1_lmin: Optional[int] = Field(100, ge=0, description="Drop m = 1 above this l (null: keep).")
    lcurve: bool = Field(True, description="Compute an L-curve over 200 eps values.")
    prior_map: Optional[str] = Field(None, description="HEALPix FITS map for method: prior.")
    stokes: list[Literal["I", "Q", "U", "V"]] = Field(
        ["I"], description="Stokes parameters to image: [I] (the scalar power-beam path) or [I, Q, U, V] (full "
        "Stokes from xx, yy, xy, yx through an E-field beam: beam type short_dipole or a pyuvdata E-field beam; "
        "docs/stokes.md).")
    eps_pol: Optional[float] = Field(None, gt=0, description="Regularisation of Q, U (E, B) and V with stokes "
                                     "[I, Q, U, V] (null: 100 x eps, the prior of a weakly polarised sky).")
    stokes_lmax: Optional[int] = Field(None, ge=2, description="Band limit of Q, U and V (their E, B, V "
                                       "harmonics) with stokes [I, Q, U, V]; I keeps mmode.lmax (null: "
                                       "min(mmode.lmax, 256): the polarised sky at ~0.7 deg, ~7x the Stokes-I "
                                       "Gram at lmax 1000 instead of 64x; docs/stokes.md).")

    @field_validator("stokes")
    @classmethod
    def _stokes(cls, v):
        if v not in (["I"], ["I", "Q", "U", "V"]):
            raise BadValue(f"{v}", "give [I] or [I, Q, U, V] (the four are solved together)")
        return v


#: this stage's sections of the workflow schema, in order
SECTIONS = {"imaging": ImagingConfig}
