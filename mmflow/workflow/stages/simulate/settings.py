"""The ``simulate`` stage's settings (:data:`SECTIONS`): the ``sky:`` and ``corrupt:`` sections of a workflow
(:class:`SkyConfig`, :class:`CorruptConfig`).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes them from here, in the
pipeline's order.
"""
from __future__ import annotations


from pydantic import Field

from mmflow.workflow.config.base import CATALOG_NAMES, Section


class SkyConfig(Section):
    """Simulated sky for the simulate stage."""

    diffuse: bool = Field(True, description="Include the synthetic Galaxy-like diffuse sky.")
    diffuse_lmax: int = Field(64, ge=1, description="Band limit of the synthetic diffuse sky.")
    sources: list[str] = Field(["Cyg A", "Cas A", "Vir A", "Tau A"], description="Catalogue sources.",
                               json_schema_extra={"allowed": "names from mmflow.sky.sources.CATALOG "
                                                  "(Cyg A, Cas A, Vir A, Tau A, Her A, Hya A, 3C 123, 3C 353, ...)"})
    resolved: bool = Field(False, description="Simulate Cyg A and Cas A resolved (2 and 3 Gaussian components, "
                           "mmflow.sky.sources.RESOLVED_COMPONENTS); every other stage keeps the catalogue's point "
                           "models unless the models stage fits them (docs/calibration.md).")
    sun: bool = Field(False, description="Add the quiet Sun: a 20' disc of 2e4 Jy at 74 MHz with spectral index "
                      "+1.8, at its apparent position at each time chunk's mid time "
                      "(mmflow.simulate.corrupt.sun_points).")
    noise: bool = Field(True, description="Add radiometer-equation thermal noise (needs telescope.include_autos).")
    polarised: dict[str, tuple[float, float, float]] = Field(
        {}, description="Fractional polarisation (Q/I, U/I, V/I; IAU) of sources in sky.sources, e.g. "
        "{3C 286: [0.1, 0.05, 0.0]}, the others unpolarised. With imaging.stokes [I, Q, U, V] the simulate "
        "stage writes xx, yy, xy and yx through the E-field beam (mmflow.simulate.polarised: direct sums); "
        "needs corrupt.enabled false.")
    seed: int = Field(1, ge=0, description="Random seed (diffuse sky and noise).")
    quad_oversample: int = Field(48, ge=0, description="Extra band limit of the simulator's sky quadrature grid.")


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


#: this stage's sections of the workflow schema, in order
SECTIONS = {"sky": SkyConfig, "corrupt": CorruptConfig}
