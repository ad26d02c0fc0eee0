"""The schema sections of the per-integration half: the corrupted simulation, gain calibration,
peeling and terrestrial removal (``docs/calibration.md``)."""
from __future__ import annotations

import math
from typing import Annotated, Literal, Union

from pydantic import BeforeValidator, Field

from mmflow.workflow.config.base import CATALOG_NAMES, Section
from mmflow.workflow.config.errors import BadValue




def _baseline_cut(v):
    """``auto`` or a number of wavelengths >= 0."""
    if v == "auto":
        return v
    try:
        x = float(v) if not isinstance(v, bool) else math.nan
    except (TypeError, ValueError):
        x = math.nan
    if not (math.isfinite(x) and x >= 0):
        raise BadValue("not auto or a number >= 0", "use auto, or a baseline length in wavelengths >= 0")
    return x


#: a baseline cut (wavelengths) or ``auto`` (:func:`mmflow.calibrate.baselines.auto_min_lambda`)
BaselineCut = Annotated[Union[Literal["auto"], float], BeforeValidator(_baseline_cut)]
CUT_ALLOWED = {"allowed": "auto, or a number >= 0"}
AUTO_CUT = ("'auto' (the default): 15, lowered per channel until every antenna keeps at least half of its "
            "baselines (docs/calibration.md); a cut that leaves an antenna fewer than 3 is refused before work.")


class CorruptConfig(Section):
    """Corruptions of the simulated drift scan (``mmflow.simulate.corrupt``); when enabled the data
    hold XX and YY (and XY, YX for full Stokes), each feed with its own gains, and noise, for calibrate,
    peel and terrestrial to undo."""

    enabled: bool = Field(False, description="Corrupt the simulation (data then hold XX and YY).")
    seed: int = Field(7, ge=0, description="Random seed of the corruptions.")
    gains: bool = Field(True, description="Per-antenna, per-pol complex gains: bandpass and a slow phase drift.")
    sawtooth_db: float = Field(0.1, ge=0, description="HVAC gain sawtooth, peak to peak in power (dB; 0 = off).")
    dd_sources: list[str] = Field(["Cyg A", "Cas A"], description="Sources of sky.sources given direction-"
                                  "dependent gains (ionospheric offsets and scintillation).",
                                  json_schema_extra=CATALOG_NAMES)
    ionosphere_arcmin: float = Field(20.0, ge=0, description="Largest refractive offset at 36.5 MHz (scales nu^-2).")
    scintillation: float = Field(0.2, ge=0, description="Scintillation log-amplitude sigma at 36.5 MHz (nu^-2).")
    crosstalk_jy: float = Field(0.0, ge=0, description="Constant rank-1 cross-talk pattern (Jy; 0 = off).")
    rfi_jy: float = Field(0.0, ge=0, description="Near-field RFI source 10 km west on the horizon (Jy; 0 = off).")
    system_jy: float = Field(0.0, ge=0, description="Receiver and unmodelled background power added to every "
                             "autocorrelation (Jy): it sets the radiometer noise and dominates real autos.")
    leakage: float = Field(0.0, ge=0, lt=1, description="Polarisation leakage (D-terms) of each antenna's feeds: "
                           "|d| uniform in [leakage/5, leakage], random phases (full-Stokes simulations: "
                           "imaging.stokes [I, Q, U, V]; 0 = off).")

