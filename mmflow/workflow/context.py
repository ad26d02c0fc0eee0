"""What every task needs, rebuilt cheaply in each worker process from the configuration."""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from mmflow.telescope import Telescope, load_layout, ovro_lwa_layout
from mmflow.telescope.beams import make_beam
from mmflow.workflow.config import WorkflowConfig
from mmflow.workflow.rundir import RunDir

SIDEREAL_DAY_S = 86164.0905


@dataclass(frozen=True)
class Context:
    """Picklable handle: the configuration (as JSON) and the run directory."""

    config_json: str
    run_path: str

    @property
    def cfg(self) -> WorkflowConfig:
        return _parse(self.config_json)

    @property
    def run(self) -> RunDir:
        return RunDir(self.run_path)

    def telescope(self) -> Telescope:
        """The telescope as stored with the visibilities (layout, baselines, frequencies)."""
        return _telescope(self.config_json, self.run_path)


@lru_cache(maxsize=8)
def _parse(js):
    return WorkflowConfig.model_validate_json(js)


@lru_cache(maxsize=8)
def _telescope(js, run_path):
    import zarr

    from mmflow.telescope.layout import Layout

    g = zarr.open_group(str(RunDir(run_path).store("vis.zarr")), mode="r")
    a = g.attrs.asdict()
    layout = Layout(a["antenna_names"], np.asarray(g["antenna_enu"][:]), a["lat_deg"], a["lon_deg"],
                    a["height_m"], a.get("layout_provenance", ""))
    tel = build_telescope(_parse(js), layout)
    tel.pairs = np.asarray(g["pairs"][:])
    tel.freqs_hz = np.asarray(g["freqs_hz"][:])
    return tel


def build_telescope(cfg, layout=None):
    """Telescope from the config (or from an ingested layout)."""
    t = cfg.telescope
    if layout is None:
        if t.preset is not None and t.layout_file is None:
            layout = ovro_lwa_layout(t.preset, radius_m=t.radius_m, stands=t.stands, max_antennas=t.max_antennas)
        else:
            from mmflow.errors import InputError

            if t.layout_file is None or t.lat_deg is None or t.lon_deg is None:
                raise InputError("workflow", "telescope.layout_file", "no layout given",
                                 "set telescope.preset, or layout_file with lat_deg and lon_deg")
            layout = load_layout(t.layout_file, t.lat_deg, t.lon_deg).select(t.stands, t.radius_m)
    beam_spec = cfg.beam.model_dump()
    return Telescope(layout, make_beam(beam_spec), np.asarray(cfg.observation.freqs_mhz) * 1e6,
                     cfg.observation.integration_s, t.include_autos, cfg.observation.channel_width_khz * 1e3)
