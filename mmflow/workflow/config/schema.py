"""One schema for every workflow YAML (pydantic); it also makes ``mmflow config init/show`` and docs.

Override any key from the command line with ``section.key=value`` (values parsed as YAML).
"""
from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, Optional, Union

import yaml
from pydantic import BaseModel, BeforeValidator, Field, ValidationError, field_validator, model_validator

from mmflow.errors import InputError
from mmflow.io.run_stores import RELEASED_BY_DEFAULT, STORES
from mmflow.mmode.splits import split_kind
from mmflow.paths import expand_path
from mmflow.workflow.config.base import Section, UserPath
from mmflow.workflow.config.beam import BEAM_PARAMS, BeamConfig
from mmflow.workflow.config.calibration import CorruptConfig
from mmflow.workflow.config.checks import beam_problems, check_config
from mmflow.workflow.stages.calibrate.settings import CalibrateConfig
from mmflow.workflow.stages.clean.settings import CleanConfig
from mmflow.workflow.stages.models.settings import ModelsConfig
from mmflow.workflow.stages.peel.settings import PeelConfig
from mmflow.workflow.stages.products.settings import ProductsConfig
from mmflow.workflow.stages.terrestrial.settings import TerrestrialConfig
from mmflow.workflow.stages.transfer.settings import TransferConfig
from mmflow.workflow.config.errors import BadValue, Origins, allowed_text, from_pydantic, report, yaml_error


class RunConfig(Section):
    """Where outputs go."""

    directory: UserPath = Field("runs/demo", description="Run directory (zarr stores, maps, status markers).",
                           json_schema_extra={"allowed": "a non-empty path"})
    name: str = Field("mmflow-run", description="A label stored with every output.")
    keep: list[str] = Field(
        [], description="Intermediate stores to keep after the stages that read them have finished (by default "
        f"{', '.join(RELEASED_BY_DEFAULT)} are then released: removed, the release recorded; every other store "
        "is kept). Names of stores, e.g. [partials.zarr]; changes no result.",
        json_schema_extra={"allowed": f"a list of {', '.join(STORES)}"})

    @field_validator("directory")
    @classmethod
    def _nonempty(cls, v):
        if not v.strip():
            raise BadValue("the run directory is empty", "give a path, e.g. run.directory=runs/my-run")
        return v

    @field_validator("keep")
    @classmethod
    def _known_stores(cls, v):
        unknown = [s for s in v if s not in set(STORES)]
        if unknown:
            raise BadValue(f"no store {', '.join(unknown)}", f"name stores of the run: {', '.join(STORES)}")
        return v


class TelescopeConfig(Section):
    """The array. Either an OVRO-LWA preset or a layout file plus a site."""

    preset: Optional[Literal["core", "full", "paper-2017", "leda512-2013"]] = Field(
        "core", description="OVRO-LWA preset from the real stand positions (give null, or just a "
        "layout_file, to use the file).")
    layout_file: Optional[UserPath] = Field(None, description="Text layout 'name east north [up]' (metres).")
    lat_deg: Optional[float] = Field(None, ge=-90, le=90, description="Site latitude for layout_file (degrees north).")
    lon_deg: Optional[float] = Field(None, ge=-180, le=360,
                                     description="Site longitude for layout_file (degrees east).")
    radius_m: Optional[float] = Field(None, gt=0, description="Keep stands within this radius of the centre.")
    stands: Optional[list[str]] = Field(None, min_length=2, description="Keep only these stand names.")
    max_antennas: Optional[int] = Field(None, ge=2, description="Keep the first N stands after the other cuts.")
    include_autos: bool = Field(True, description="Use autocorrelations as baselines of length 0.")


def _prior_passes(v):
    """``auto`` or a number of passes 0..3."""
    if v == "auto":
        return v
    if isinstance(v, bool) or not isinstance(v, (int, str)) or not str(v).strip().isdigit() or int(v) > 3:
        raise BadValue("not auto or a whole number of passes 0 to 3", "use auto (the default), or 0, 1, 2 or 3")
    return int(v)


class ObservationConfig(Section):
    """Frequencies and the drift scan that is simulated or expected."""

    freqs_mhz: Optional[list[float]] = Field(
        None, min_length=1, description="Channel centre frequencies in MHz. Simulated data: these channels "
        "(null: [40.0]). Ingested data: the file channel nearest each (refused beyond half a channel width; "
        "input.average_channels averages around it); null: every channel of the files.",
        json_schema_extra={"allowed": "null or a non-empty list of numbers > 0"})
    channel_width_khz: float = Field(24.0, gt=0, description="Channel width (radiometer noise).")
    integration_s: float = Field(13.0, gt=0, description="Integration time in seconds.")
    n_integrations: Optional[int] = Field(None, ge=1,
                                          description="Integrations to simulate (default: one sidereal day).")
    start_lst_deg: float = Field(0.0, description="LST of the first simulated integration.")
    epoch_jd: float = Field(2457802.0, gt=0, description="Epoch (UTC JD) of the frame of date (default 2017-02-18).")
    raw_files: Optional[Literal["uvh5"]] = Field(
        None, description="Simulated data: also write the drift scan as a telescope writes it, one UVH5 file per "
        "time chunk in the run directory's raw/ (pyuvdata, drift scan, pol_convention avg), for a run with "
        "source: ingest to read (docs/planning.md). null: vis.zarr only.")

    def simulated_freqs_mhz(self):
        """The channels a simulation makes: ``freqs_mhz``, or 40 MHz when it is null."""
        return list(self.freqs_mhz) if self.freqs_mhz is not None else [40.0]

    @field_validator("freqs_mhz")
    @classmethod
    def _positive(cls, v):
        if v is None:
            return v
        bad = [f for f in v if f <= 0]
        if bad:
            raise BadValue(f"non-positive frequencies {bad}", "give channel centre frequencies in MHz, all > 0")
        return v


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


class InputConfig(Section):
    """Existing data for the ingest stage."""

    path: Optional[UserPath] = Field(None, description="File or glob of UVH5 / uvfits / MS files.")
    format: Optional[Literal["uvh5", "uvfits", "ms"]] = Field(None, description="Force a format.")
    on_bad_file: Literal["error", "skip"] = Field("error", description="Stop, or log and count a skip.")
    nonfinite: Literal["error", "flag"] = Field(
        "error", description="Unflagged NaN/inf samples in input files: refuse the file, or flag them "
        "(counted and logged).")
    pol_convention: Literal["auto", "sum", "avg"] = Field(
        "auto", description="How the files' XX / YY relate to Stokes I (pyuvdata's pol_convention): 'sum' "
        "I = XX + YY (matvis, pyuvsim, hera_sim: an unpolarised source of S Jy gives XX = S/2), 'avg' "
        "I = (XX + YY) / 2 (CASA-style, XX = S); data are stored in mmflow's avg convention ('sum' data "
        "doubled). 'auto': what the file says; when it says nothing, calibration sets the scale, or the run is "
        "refused before any work (docs/conventions.md).")
    cross_hands: bool = Field(True, description="Carry the cross hands (xy, yx / rl, lr) of files that hold them "
                              "in vis.zarr's vis_cross (calibration and Stokes I use the parallel hands).")
    average_channels: int = Field(1, ge=1, description="Average this many file channels into each ingested "
                                  "channel: around each of observation.freqs_mhz, or consecutive blocks when it is "
                                  "null (flags and nsample weights respected, as pyuvdata's frequency_average).")
    conjugate: bool = Field(False, description="Conjugate the data on ingest. pyuvdata data (as written by "
                            "matvis / hera_sim) already follow mmflow's exp(+2 pi i b.r), b = x_2 - x_1; set true "
                            "only for data in the opposite sign convention.")


class MmodeConfig(Section):
    """Sidereal binning and the m-mode transform."""

    lmax: int = Field(64, ge=1, description="Largest spherical-harmonic degree.")
    mmax: Optional[int] = Field(None, ge=0, description="Largest m (default lmax; at most lmax).")
    n_bins: Optional[int] = Field(None, ge=1, description="Sidereal bins (default: integrations per sidereal day; "
                                  "at least 2 mmax + 1).")
    min_coverage: float = Field(0.95, ge=0, le=1, description="Fraction of the sidereal day each baseline must "
                                "cover (below: coverage_policy); a run where most baselines fall below stops.")
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

    @field_validator("stokes")
    @classmethod
    def _stokes(cls, v):
        if v not in (["I"], ["I", "Q", "U", "V"]):
            raise BadValue(f"{v}", "give [I] or [I, Q, U, V] (the four are solved together)")
        return v


class ClusterConfig(Section):
    """Where the dask graph runs."""

    kind: Literal["local", "address", "slurm", "pbs", "synchronous"] = Field(
        "local", description="Local processes, an existing scheduler, a batch system, or in-process.")
    address: Optional[str] = Field(None, description="Scheduler address for kind=address (or DASK_SCHEDULER_ADDRESS).")
    n_workers: int = Field(2, ge=1, description="Local worker processes, or jobqueue jobs to scale to.")
    threads_per_worker: int = Field(1, ge=1, description="Threads per worker process.")
    memory_limit: str = Field("auto", description="Per-worker memory limit (dask spills/pauses above it).",
                              json_schema_extra={"allowed": "'auto', a fraction of the machine (0 < f <= 1), "
                                                 "or bytes ('4GiB', '500MB')"})
    dashboard_address: str = Field(":8787", description="Dashboard '[host]:port' (host: loopback unless expose).",
                                   json_schema_extra={"allowed": "'[host]:port', port 0-65535 (0: any free port)"})
    expose: bool = Field(False, description="Listen on all network interfaces (scheduler and dashboard); "
                         "default: 127.0.0.1 only. See docs/clusters.md for TLS.")
    worker_wait_s: float = Field(300.0, gt=0, description="Fail a stage that has had no worker for this long "
                                 "while no worker job is queued or starting (SLURM/PBS: those are waited for); "
                                 "finished chunks are kept for a rerun.")
    interface: Optional[str] = Field(None, description="SLURM/PBS: the network interface (e.g. ib0, eth1) the "
                                     "scheduler listens on, the one the compute nodes reach this machine on; "
                                     "unset: the interface on the SLURM nodes' network (sinfo), else dask's guess "
                                     "(the default route's). See docs/clusters.md.")
    jobqueue: dict = Field(default_factory=dict,
                           description="dask-jobqueue cluster options (cores, memory, queue, ...).")

    @field_validator("memory_limit", mode="before")
    @classmethod
    def _memory(cls, v):
        return check_memory_limit(v)

    @field_validator("jobqueue")
    @classmethod
    def _jobqueue(cls, v):
        if isinstance(v.get("log_directory"), str):  # SLURM and PBS do not expand their #SBATCH / #PBS lines
            v = {**v, "log_directory": expand_path(v["log_directory"])}
        return v

    @field_validator("dashboard_address", mode="before")
    @classmethod
    def _dashboard(cls, v):
        if isinstance(v, int) and not isinstance(v, bool):
            v = f":{v}"  # a bare port
        if not isinstance(v, str):
            raise BadValue("not '[host]:port'", "write e.g. ':8787' (any free port: ':0')")
        host, sep, port = v.rpartition(":")
        if not sep or not port.isdigit() or int(port) > 65535:
            raise BadValue("not '[host]:port'", "write e.g. ':8787' (any free port: ':0')")
        return v


def check_memory_limit(v):
    """``'auto'``, a fraction in (0, 1], or a byte count dask parses; returned as text."""
    from dask.utils import parse_bytes  # deferred: dask takes 0.3-0.8 s to import; `mmflow --help` loads this module

    fix = "use 'auto', a fraction of the machine's memory such as 0.5, or bytes such as '4GiB'"
    if isinstance(v, bool):
        raise BadValue("not a memory size", fix)
    if isinstance(v, (int, float)):
        if v <= 0:
            raise BadValue("must be positive", fix)
        return str(v)
    if not isinstance(v, str):
        raise BadValue("not a memory size", fix)
    if v.strip().lower() == "auto":
        return "auto"
    try:
        x = float(v)
    except ValueError:
        try:
            x = parse_bytes(v)
        except (ValueError, TypeError):
            raise BadValue("not a memory size", fix) from None
    if x <= 0:
        raise BadValue("must be positive", fix)
    return v.strip()


class WorkflowConfig(Section):
    """A whole mmflow workflow."""

    run: RunConfig = RunConfig()
    source: Literal["simulate", "ingest"] = Field("simulate", description="Make data, or read it.")
    telescope: TelescopeConfig = TelescopeConfig()
    beam: BeamConfig = BeamConfig()
    observation: ObservationConfig = ObservationConfig()
    sky: SkyConfig = SkyConfig()
    input: InputConfig = InputConfig()
    corrupt: CorruptConfig = CorruptConfig()
    calibrate: CalibrateConfig = CalibrateConfig()
    models: ModelsConfig = ModelsConfig()
    peel: PeelConfig = PeelConfig()
    terrestrial: TerrestrialConfig = TerrestrialConfig()
    mmode: MmodeConfig = MmodeConfig()
    transfer: TransferConfig = TransferConfig()
    imaging: ImagingConfig = ImagingConfig()
    clean: CleanConfig = CleanConfig()
    products: ProductsConfig = ProductsConfig()
    cluster: ClusterConfig = ClusterConfig()


def _read_file(path, origins):
    src = str(path)
    p = Path(path)
    if not p.exists():
        raise InputError(src, "workflow", "file not found", "give the path of a workflow YAML (see workflows/)")
    text = p.read_text()
    try:
        data = yaml.safe_load(text)
        origins.add_yaml(src, text)
    except yaml.YAMLError as exc:
        raise yaml_error(src, exc) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(src, "(top level)", f"the file holds a {type(data).__name__}, not a mapping of sections",
                         "write sections at the top level, e.g. 'mmode:' then indented 'lmax: 64' "
                         "(see `mmflow config show`)")
    return data


def _apply_override(data, item, origins):
    where = f"command-line override '{item}'"
    if "=" not in item:
        raise InputError(where, item, "override without '='", "write section.key=value")
    key, text = item.split("=", 1)
    key = key.strip()
    parts = key.split(".")
    if not key or not all(parts):
        raise InputError(where, key, "empty key", "write section.key=value, e.g. imaging.eps=0.001")
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise yaml_error(where, exc) from None
    d = data
    for i, p in enumerate(parts[:-1]):
        d = d.setdefault(p, {})
        if not isinstance(d, dict):
            raise InputError(where, ".".join(parts[: i + 1]), f"'{p}' is not a section",
                             "use section.key=value")
    d[parts[-1]] = value
    origins.add_override(tuple(parts), item)


def load_config(path=None, overrides=()):
    """Read a workflow YAML, apply ``key=value`` overrides and validate everything.

    The schema (each field's type and range), the cross-field rules and the files the
    configuration names (layout, beam, prior map) are all checked here, before any cluster
    starts or stage runs; nothing is written. Errors name the file and line, or the
    command-line override, that set each bad value, the field, the value and the fix.

    Raises
    ------
    InputError
        A missing file or a YAML syntax error.
    ConfigError
        (an ``InputError``) every bad value, one line each.
    """
    origins = Origins(str(path) if path else "<defaults>")
    data = _read_file(path, origins) if path else {}
    for item in overrides:
        _apply_override(data, item, origins)
    problems, cfg = [], None
    try:
        cfg = WorkflowConfig.model_validate(data)
    except ValidationError as exc:
        problems = from_pydantic(exc.errors(), WorkflowConfig,
                                 {("beam",): [k for m in BEAM_PARAMS.values() for k in m.model_fields]})
    problems += beam_problems(data.get("beam", {}))
    report(problems, origins)
    t = cfg.telescope
    if t.layout_file is not None and "preset" not in data.get("telescope", {}):
        cfg.telescope = t.model_copy(update={"preset": None})  # the default preset gives way to a layout file
    if cfg.clean.enabled and "splits" not in (data.get("mmode") or {}):
        # CLEAN's threshold is a multiple of the jackknife noise: the splits it needs come with it
        cfg.mmode = cfg.mmode.model_copy(update={"splits": ["full", "even", "odd"]})
    report(check_config(cfg), origins)
    return cfg


def _option_line(indent, name, field, value):
    """``name: value  # description [allowed values]`` (value as YAML flow)."""
    if field.is_required():
        dumped = "(required)"
    else:
        dumped = yaml.safe_dump(value, default_flow_style=True).strip()
        dumped = dumped.removesuffix("\n...").removesuffix("...").strip()
    desc = (field.description or "").rstrip(".")
    note = f"{desc}. [{allowed_text(field)}]" if desc else f"[{allowed_text(field)}]"
    return " " * indent + f"{field.alias or name}: {dumped}  # {note}"


def _beam_lines(indent):
    """The parameters of every beam type: the default type's as options, the others commented."""
    default = BeamConfig().type
    lines = []
    for kind, model in BEAM_PARAMS.items():
        doc = (model.__doc__ or "").strip().splitlines()[0]
        if kind == default:
            lines.append(" " * indent + f"# parameters of type {doc}")
            lines.extend(_option_line(indent, n, f, f.get_default(call_default_factory=True))
                         for n, f in model.model_fields.items())
    lines.append(" " * indent + "# parameters of the other types (give the whole section, e.g. "
                 "beam={type: gaussian, fwhm_deg: 30}):")
    for kind, model in BEAM_PARAMS.items():
        if kind != default:
            lines.append(" " * indent + f"# type {(model.__doc__ or '').strip().splitlines()[0]}")
            lines.extend(" " * indent + "#   " + _option_line(0, n, f, None if f.is_required() else
                                                            f.get_default(call_default_factory=True))
                         for n, f in model.model_fields.items())
    return lines


def schema_yaml():
    """A commented YAML of every option: default, description and allowed values.

    It drives ``mmflow config show`` / ``config init`` and docs/configuration.md; the beam
    section lists the parameters of every beam type.
    """
    lines = ["# mmflow workflow: every option with its default and [allowed values]", ""]

    def walk(model, indent):
        for name, field in type(model).model_fields.items():
            val = getattr(model, name)
            if isinstance(val, BaseModel):
                doc = (type(val).__doc__ or "").strip().splitlines()
                lines.append(" " * indent + f"{name}:" + (f"  # {doc[0]}" if doc else ""))
                walk(val, indent + 2)
            else:
                lines.append(_option_line(indent, name, field, val))
        if isinstance(model, BeamConfig):
            lines.extend(_beam_lines(indent))

    walk(WorkflowConfig(), 0)
    return "\n".join(lines) + "\n"
