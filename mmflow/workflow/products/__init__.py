"""Product builders of the ``products`` stage (:mod:`mmflow.workflow.stages.products`), not stages.

:mod:`.clean`: CLEAN's maps, PSF stamps and Table 1 (docs/clean.md); :mod:`.science`: the flux
scale, astrometric registration and spectral-index products (docs/products.md).
"""
