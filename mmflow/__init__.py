"""mmflow: full-sky maps from drift-scanning interferometers by m-mode analysis imaging.

Conventions (sidereal angle, m-mode sign, a_lm normalisation, transfer-coefficient
definition, units) are pinned down in ``docs/conventions.md`` and in
:mod:`mmflow.conventions`.
"""
from mmflow import compiled_cache as _compiled_cache
from mmflow import offline as _offline

_offline.configure_astropy()
_compiled_cache.configure_numba_cache()

__version__ = "0.1.0"
