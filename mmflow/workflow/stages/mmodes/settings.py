"""The ``mmodes`` stage's settings (:data:`SECTIONS`): the ``mmode:`` section of a workflow
(:class:`MmodeConfig`; ``mmode.lmax`` is every later stage's band limit).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes them from here, in the
pipeline's order.
"""
from __future__ import annotations

from typing import Annotated, Literal, Optional, Union

from pydantic import BeforeValidator, Field, field_validator, model_validator

from mmflow.mmode.splits import split_kind
from mmflow.workflow.config.base import Section, UserPath
from mmflow.workflow.config.errors import BadValue


def _prior_passes(v):
    """``auto`` or a number of passes 0..3."""
    if v == "auto":
        return v
    if isinstance(v, bool) or not isinstance(v, (int, str)) or not str(v).strip().isdigit() or int(v) > 3:
        raise BadValue("not auto or a whole number of passes 0 to 3", "use auto (the default), or 0, 1, 2 or 3")
    return int(v)


class MmodeConfig(Section):
    """Sidereal binning and the m-mode transform."""

    lmax: int = Field(64, ge=1, description="Largest spherical-harmonic degree.")
    mmax: Optional[int] = Field(None, ge=0, description="Largest m (default lmax; at most lmax).")
    n_bins: Optional[int] = Field(None, ge=1, description="Sidereal bins (default: integrations per sidereal day; "
                                  "at least 2 mmax + 1).")
    min_coverage: float = Field(0.7, ge=0, le=1, description="Fraction of the sidereal day each baseline must "
                                "cover, flagged time counted as missing (below: coverage_policy); a run where most "
                                "baselines fall below stops. The default leaves a day with up to 30 % flagged or "
                                "unobserved to the m-modes' least squares and its prior passes (docs/mmodes.md).")
    baseline_chunk: int = Field(256, ge=1, description="Baselines per task in the corner turn.")
    splits: list[str] = Field(
        ["full"], description="Data splits carried through m-modes, right-hand sides and alm (one transfer pass "
        "for all; docs/mmodes.md; not given: [full], or [full, even, odd] when clean.enabled): 'full' first, "
        "then 'even' / 'odd' sidereal bins (jackknife halves), 'day<k>' "
        "the k-th sidereal day of the data (k = 0, 1, ...; per-day jackknife), 'day' / 'night' the integrations "
        "with the Sun above / below the horizon (a systematics check for data spanning months).",
        json_schema_extra={"allowed": "'full' first, then each of even | odd | day<k> (k = 0, 1, ...) | day | "
                           "night at most once"})
    noise: Literal["auto", "radiometer", "data"] = Field(
        "auto", description="Thermal noise per baseline: 'radiometer' sigma^2 = V_ii V_jj / (dnu tau) from the "
        "autocorrelations; 'data' from the residual of each baseline's band-limited m-mode fit (the sky removed, "
        "docs/mmodes.md); 'auto' radiometer where the autocorrelations exist, else data.")
    coverage_policy: Literal["drop", "downweight"] = Field(
        "drop", description="Baselines whose sidereal coverage is below min_coverage: dropped (weight 0) or "
        "down-weighted by coverage / min_coverage; counted and logged either way.")
    prior_run: Optional[UserPath] = Field(
        None, description="Run directory of a finished earlier run of the same data (same lmax, channels and "
        "epoch): its solved map's model visibilities are the prior of each baseline's m-mode fit, filling what "
        "flagged time leaves unmeasured (a second pass; docs/mmodes.md). Run it in a new run.directory. "
        "null: no prior (gaps held at 0).", json_schema_extra={"allowed": "null or a run directory"})

    prior_passes: Annotated[Union[Literal["auto"], int], BeforeValidator(_prior_passes)] = Field(
        "auto", description="Prior passes inside one run (docs/mmodes.md): after the calibration stages, m-modes "
        "-> solve run in RUN/prior0 (least squares alone), and each later pass, the run's own m-modes among them, "
        "fits flagged time with the map before it as its prior (mmode.prior_run done for you; each pass "
        "resumable). 'auto': passes only where flagged time leaves a baseline a gap longer than its band limit "
        "bridges (one Nyquist interval, N / (2 M_b + 1) sidereal bins), until the map changes by less than "
        "prior_tolerance, at most prior_max_passes; none without such gaps (and none with prior_run). 0: none.",
        json_schema_extra={"allowed": "auto, or 0 to 3", "fingerprint_as": 0})
    prior_tolerance: float = Field(
        0.02, gt=0, description="'auto' prior passes stop when the map's alm (every channel, first split) changes "
        "by less than this from one pass to the next: ||a_k - a_(k-1)|| / ||a_k||.",
        json_schema_extra={"fingerprint": False})
    prior_max_passes: int = Field(3, ge=1, le=6, description="The most 'auto' prior passes (each costs the imaging "
                                  "stages once more).", json_schema_extra={"fingerprint": False})

    @model_validator(mode="after")
    def _one_prior(self):
        if self.prior_passes != "auto" and self.prior_passes and self.prior_run is not None:
            raise BadValue("mmode.prior_passes and mmode.prior_run both give a prior",
                           "use prior_passes (passes inside this run) or prior_run (an earlier run), not both")
        return self

    @field_validator("prior_run")
    @classmethod
    def _prior_path(cls, v):
        if v is not None and not v.strip():
            raise BadValue("the prior run directory is empty", "give an earlier run's run.directory, or null")
        return v

    @field_validator("splits")
    @classmethod
    def _full_first(cls, v):
        for s in v:
            try:
                split_kind(s)
            except ValueError:
                raise BadValue(f"unknown split '{s}'", "use full, even, odd, day<k> (k = 0, 1, ...: the k-th "
                               "sidereal day), day or night, e.g. mmode.splits=[full, day0, day1]") from None
        if not v or v[0] != "full" or len(set(v)) != len(v):
            raise BadValue("'full' must come first and each split once", "write e.g. mmode.splits=[full, even, odd]")
        return v


#: this stage's sections of the workflow schema, in order
SECTIONS = {"mmode": MmodeConfig}
