"""What the per-integration stages' settings share (calibrate, peel and terrestrial: their
``settings.py``): the baseline cut's type and its words (``docs/calibration.md``)."""
from __future__ import annotations

import math
from typing import Annotated, Literal, Union

from pydantic import BeforeValidator

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


