"""What every section of the workflow schema shares: strict sections and common value checks."""
from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict

from mmflow.paths import expand_path

from mmflow.workflow.config.errors import BadValue


class Section(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


def power_of_two(v):
    if v is not None and (v < 1 or v > 2**29 or v & (v - 1)):
        lo = 1 << max(0, int(v).bit_length() - 1)
        raise BadValue("HEALPix nside must be a power of two", f"use {lo} or {2 * lo} (or null for the default)")
    return v


#: schema annotation of fields that take catalogue source names
CATALOG_NAMES = {"allowed": "names from mmflow.sky.sources.CATALOG"}


#: a path setting: ``~`` and environment variables expanded when the configuration is read
#: (:func:`mmflow.paths.expand_path`), so every reader of the field gets the same path
UserPath = Annotated[str, AfterValidator(expand_path)]
