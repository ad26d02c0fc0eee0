"""The ``ingest`` stage's settings (:data:`SECTIONS`): the ``input:`` section of a workflow
(:class:`InputConfig`).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes them from here, in the
pipeline's order.
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field

from mmflow.workflow.config.base import Section, UserPath


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


#: this stage's sections of the workflow schema, in order
SECTIONS = {"input": InputConfig}
