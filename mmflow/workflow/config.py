"""One schema for every workflow YAML (pydantic); it also makes ``mmflow config init/show`` and docs.

Override any key from the command line with ``section.key=value`` (values parsed as YAML).
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Literal, Optional

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from mmflow.errors import InputError


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class RunConfig(_Section):
    """Where outputs go."""

    directory: str = Field("runs/demo", description="Run directory (zarr stores, maps, status markers).")
    name: str = Field("mmflow-run", description="A label stored with every output.")


class TelescopeConfig(_Section):
    """The array. Either an OVRO-LWA preset or a layout file plus a site."""

    preset: Optional[Literal["core", "full", "paper-2017", "leda512-2013"]] = Field(
        "core", description="OVRO-LWA preset from the real stand positions; null to use layout_file.")
    layout_file: Optional[str] = Field(None, description="Text layout 'name east north [up]' (metres).")
    lat_deg: Optional[float] = Field(None, description="Site latitude for layout_file.")
    lon_deg: Optional[float] = Field(None, description="Site longitude for layout_file.")
    radius_m: Optional[float] = Field(None, description="Keep stands within this radius of the centre.")
    stands: Optional[list[str]] = Field(None, description="Keep only these stand names.")
    max_antennas: Optional[int] = Field(None, description="Keep the first N stands after the other cuts.")
    include_autos: bool = Field(True, description="Use autocorrelations as baselines of length 0.")


class BeamConfig(_Section):
    """Primary beam (Stokes-I power, 1 at zenith)."""

    model_config = ConfigDict(extra="allow")
    type: Literal["sin_elevation", "gaussian", "zernike", "pyuvdata"] = "sin_elevation"


class ObservationConfig(_Section):
    """Frequencies and the drift scan that is simulated or expected."""

    freqs_mhz: list[float] = Field([40.0], description="Channel centre frequencies in MHz.")
    channel_width_khz: float = Field(24.0, description="Channel width (radiometer noise).")
    integration_s: float = Field(13.0, description="Integration time in seconds.")
    n_integrations: Optional[int] = Field(None, description="Integrations to simulate (default: one sidereal day).")
    start_lst_deg: float = Field(0.0, description="LST of the first simulated integration.")
    epoch_jd: float = Field(2457802.0, description="Epoch (UTC JD) of the frame of date (default 2017-02-18).")

    @field_validator("freqs_mhz")
    @classmethod
    def _positive(cls, v):
        if not v or any(f <= 0 for f in v):
            raise ValueError("give at least one positive frequency in MHz")
        return v


class SkyConfig(_Section):
    """Simulated sky for the simulate stage."""

    diffuse: bool = Field(True, description="Include the synthetic Galaxy-like diffuse sky.")
    diffuse_lmax: int = Field(64, description="Band limit of the synthetic diffuse sky.")
    sources: list[str] = Field(["Cyg A", "Cas A", "Vir A", "Tau A"], description="Catalogue sources.")
    noise: bool = Field(True, description="Add radiometer-equation thermal noise.")
    seed: int = Field(1, description="Random seed (diffuse sky and noise).")
    quad_oversample: int = Field(48, description="Extra band limit of the simulator's sky quadrature grid.")


class InputConfig(_Section):
    """Existing data for the ingest stage."""

    path: Optional[str] = Field(None, description="File or glob of UVH5 / uvfits / MS files.")
    format: Optional[Literal["uvh5", "uvfits", "ms"]] = Field(None, description="Force a format.")
    on_bad_file: Literal["error", "skip"] = Field("error", description="Stop, or log and count a skip.")
    conjugate: bool = Field(False, description="Conjugate the data on ingest. pyuvdata data (as written by "
                            "matvis / hera_sim) already follow mmflow's exp(+2 pi i b.r), b = x_2 - x_1; set true "
                            "only for data in the opposite sign convention.")


class StageSwitch(_Section):
    enabled: bool = False


class MmodeConfig(_Section):
    """Sidereal binning and the m-mode transform."""

    lmax: int = Field(64, description="Largest spherical-harmonic degree.")
    mmax: Optional[int] = Field(None, description="Largest m (default lmax).")
    n_bins: Optional[int] = Field(None, description="Sidereal bins (default: integrations per sidereal day).")
    min_coverage: float = Field(0.95, description="Fraction of the sidereal day that must hold data.")
    baseline_chunk: int = Field(256, description="Baselines per task in the corner turn.")
    splits: list[Literal["full", "even", "odd"]] = Field(
        ["full"], description="Data splits carried through m-modes, right-hand sides and alm: 'full' first, "
        "then e.g. 'even' and 'odd' sidereal bins for jackknife noise maps (one transfer pass for all).")
    noise: Literal["data", "radiometer"] = Field(
        "data", description="Noise per baseline from successive-integration differences, or from the "
        "radiometer equation sigma^2 = V_ii V_jj / (dnu tau) with the autocorrelations.")


    @field_validator("splits")
    @classmethod
    def _full_first(cls, v):
        if not v or v[0] != "full" or len(set(v)) != len(v):
            raise ValueError("list 'full' first, then other splits once each, e.g. [full, even, odd]")
        return v


class TransferConfig(_Section):
    """Transfer matrices and normal equations."""

    mode: Literal["normal", "store"] = Field("normal", description="'normal': stream G_m; 'store': also write B_m.")
    dtype: Literal["float32", "float64"] = "float64"
    baseline_chunk: int = Field(32, description="Baselines per transfer task (memory ~ chunk * lmax^2 * 16 B).")
    per_baseline_lmax: bool = True
    m_block: int = Field(16, description="m values per reduction / solve task.")
    groups: int = Field(8, description="Baseline groups of the transfer stage: tasks per frequency, and partial "
                        "normal equations kept on disk (each ~ the Gram's size). Set >= the cluster's worker "
                        "threads for parallelism. Results never depend on the cluster.")
    noise_weighting: bool = Field(True, description="Weight baselines by 1/variance in G_m (minimum variance).")


class ImagingConfig(_Section):
    method: Literal["tikhonov", "min_variance", "moore_penrose", "prior", "smoothness"] = "tikhonov"
    eps: float = Field(0.01, description="Regularisation parameter (paper: 0.01).")
    zero_monopole: bool = True
    filter_m0: bool = True
    filter_m1_lmin: Optional[int] = 100
    lcurve: bool = Field(True, description="Compute an L-curve over 200 eps values.")
    prior_map: Optional[str] = None


class ProductsConfig(_Section):
    nside: Optional[int] = Field(None, description="Output HEALPix nside (default from lmax).")
    frame: Literal["icrs", "galactic", "date"] = "icrs"
    unit: Literal["K", "Jy/sr"] = "K"
    png: bool = True


class ClusterConfig(_Section):
    """Where the dask graph runs."""

    kind: Literal["local", "address", "slurm", "pbs", "synchronous"] = "local"
    address: Optional[str] = Field(None, description="Scheduler address for kind=address (or DASK_SCHEDULER_ADDRESS).")
    n_workers: int = Field(2, description="Local worker processes, or jobqueue jobs to scale to.")
    threads_per_worker: int = 1
    memory_limit: str = Field("auto", description="Per-worker memory limit (dask spills/pauses above it).")
    dashboard_address: str = ":8787"
    worker_wait_s: float = Field(300.0, gt=0, description="Fail a stage that has had no worker for this long "
                                 "(workers died: memory, walltime); finished chunks are kept for a rerun.")
    jobqueue: dict = Field(default_factory=dict, description="dask-jobqueue cluster options (cores, memory, queue, ...).")


class WorkflowConfig(_Section):
    """A whole mmflow workflow."""

    run: RunConfig = RunConfig()
    source: Literal["simulate", "ingest"] = Field("simulate", description="Make data, or read it.")
    telescope: TelescopeConfig = TelescopeConfig()
    beam: BeamConfig = BeamConfig()
    observation: ObservationConfig = ObservationConfig()
    sky: SkyConfig = SkyConfig()
    input: InputConfig = InputConfig()
    calibrate: StageSwitch = StageSwitch()
    peel: StageSwitch = StageSwitch()
    terrestrial: StageSwitch = StageSwitch()
    mmode: MmodeConfig = MmodeConfig()
    transfer: TransferConfig = TransferConfig()
    imaging: ImagingConfig = ImagingConfig()
    clean: StageSwitch = StageSwitch()
    products: ProductsConfig = ProductsConfig()
    cluster: ClusterConfig = ClusterConfig()


def _set_dotted(d, key, value):
    parts = key.split(".")
    for p in parts[:-1]:
        d = d.setdefault(p, {})
        if not isinstance(d, dict):
            raise InputError("override", key, f"'{p}' is not a section", "use section.key=value")
    d[parts[-1]] = value


def load_config(path=None, overrides=()):
    """Read a workflow YAML, apply ``key=value`` overrides, validate; errors name file and field."""
    data = {}
    src = str(path) if path else "<defaults>"
    if path:
        p = Path(path)
        if not p.exists():
            raise InputError(src, "workflow", "file not found", "give the path of a workflow YAML (see workflows/)")
        data = yaml.safe_load(p.read_text()) or {}
    for item in overrides:
        if "=" not in item:
            raise InputError("command line", item, "override without '='", "write section.key=value")
        k, v = item.split("=", 1)
        _set_dotted(data, k.strip(), yaml.safe_load(v))
    for sec, key in (("run", "directory"), ("input", "path")):
        val = data.get(sec, {}).get(key) if isinstance(data.get(sec), dict) else None
        if isinstance(val, str):
            data[sec][key] = os.path.expanduser(os.path.expandvars(val))
    try:
        return WorkflowConfig.model_validate(data)
    except ValidationError as exc:
        msgs = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise InputError(src, "config", msgs, "see `mmflow config show` for the schema and defaults") from None


def config_fingerprint(cfg, sections):
    """Hash of the named config sections (decides whether stored outputs are stale)."""
    blob = json.dumps({s: getattr(cfg, s).model_dump() if hasattr(getattr(cfg, s), "model_dump")
                       else getattr(cfg, s) for s in sections}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def schema_yaml():
    """A commented YAML of every option with its default and description."""
    lines = ["# mmflow workflow: every option with its default", ""]

    def walk(model, indent):
        for name, field in type(model).model_fields.items():
            val = getattr(model, name)
            desc = field.description
            if isinstance(val, BaseModel):
                doc = (type(val).__doc__ or "").strip().splitlines()
                lines.append(" " * indent + f"{name}:" + (f"  # {doc[0]}" if doc else ""))
                walk(val, indent + 2)
            else:
                dumped = yaml.safe_dump(val, default_flow_style=True).strip()
                dumped = dumped.removesuffix("\n...").removesuffix("...").strip()
                lines.append(" " * indent + f"{name}: {dumped}" + (f"  # {desc}" if desc else ""))

    walk(WorkflowConfig(), 0)
    return "\n".join(lines) + "\n"
