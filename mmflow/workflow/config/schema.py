"""One schema for every workflow YAML (pydantic); it also makes ``mmflow config init/show`` and docs.

Override any key from the command line with ``section.key=value`` (values parsed as YAML).
"""
from __future__ import annotations

import importlib.util
from importlib import import_module
from pathlib import Path
from typing import Literal, Optional

import yaml
from pydantic import BaseModel, Field, ValidationError, create_model, field_validator

from mmflow.errors import InputError
from mmflow.io.run_stores import RELEASED_ARRAYS, RELEASED_BY_DEFAULT, STORES
from mmflow.paths import expand_path
from mmflow.workflow.config.base import Section, UserPath
from mmflow.workflow.config.beam import BEAM_PARAMS, BeamConfig
from mmflow.workflow.config.checks import beam_problems, check_config
from mmflow.workflow.stages import ORDER
from mmflow.workflow.config.errors import BadValue, Origins, allowed_text, from_pydantic, report, yaml_error


class RunConfig(Section):
    """Where outputs go."""

    directory: UserPath = Field("runs/demo", description="Run directory (zarr stores, maps, status markers).",
                           json_schema_extra={"allowed": "a non-empty path"})
    name: str = Field("mmflow-run", description="A label stored with every output.")
    keep: list[str] = Field(
        [], description="Intermediate stores to keep after the stages that read them have finished (by default "
        f"{', '.join(RELEASED_BY_DEFAULT)} are then released: removed, the release recorded; and the large arrays "
        f"of {', '.join(RELEASED_ARRAYS)} that later stages do not read: docs/stores.md; every other store is "
        "kept). Names of stores, kept whole, e.g. [partials.zarr, vis.zarr]; changes no result.",
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


def stage_sections(order=ORDER):
    """``{section: Section class}`` of every stage that owns settings (``stages/<name>/settings.py``'s
    ``SECTIONS``), in run order (:data:`mmflow.workflow.stages.ORDER`, which the pipeline is built from:
    adding a stage with settings adds its sections to the schema)."""
    out = {}
    for name in order:
        module = f"mmflow.workflow.stages.{name}.settings"
        if importlib.util.find_spec(module) is not None:
            out.update(import_module(module).SECTIONS)
    return out


#: the sections every stage shares: the run, the data's description (before the stages' own), the cluster (after)
SHARED_FIRST = {"run": RunConfig, "telescope": TelescopeConfig, "beam": BeamConfig, "observation": ObservationConfig}
SHARED_LAST = {"cluster": ClusterConfig}

#: A whole mmflow workflow: ``source`` (make data, or read it), the shared sections, then each stage's
#: own (:func:`stage_sections`) in the pipeline's order
WorkflowConfig = create_model(
    "WorkflowConfig", __base__=Section, __module__=__name__, __doc__="A whole mmflow workflow.",
    run=(RunConfig, RunConfig()),
    source=(Literal["simulate", "ingest"], Field("simulate", description="Make data, or read it.")),
    **{k: (c, c()) for k, c in {**SHARED_FIRST, **stage_sections(), **SHARED_LAST}.items() if k != "run"})


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
