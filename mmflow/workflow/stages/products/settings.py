"""The ``products`` stage's settings: the ``products:`` section of a workflow (:class:`ProductsConfig`).

The schema (:class:`mmflow.workflow.config.schema.WorkflowConfig`) takes it from here.
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator

from mmflow.workflow.config.base import Section, power_of_two


class ProductsConfig(Section):
    """Maps, plots, science products (flux scale, spectral index, astrometry), HTML report.

    See docs/products.md.
    """

    nside: Optional[int] = Field(None, description="Output HEALPix nside (default from lmax).",
                                 json_schema_extra={"allowed": "a power of two (1, 2, 4, ..., 2^29), or null"})
    frame: Literal["icrs", "galactic", "date"] = Field("icrs", description="Coordinate frame of the maps.")
    unit: Literal["K", "Jy/sr"] = Field("K", description="Brightness temperature or intensity.")
    png: bool = Field(True, description="Also write Mollweide and L-curve PNGs.")
    flux_scale: bool = Field(True, description="Measure the catalogue sources' fluxes in each channel's map "
                             "(disc sum minus annulus median over the PSF's, per source) and plot them against "
                             "their published spectra.")
    flux_scale_sources: Optional[list[str]] = Field(None, description="Catalogue sources to measure (null: every "
                                                    "catalogue source the array sees; peeled sources are taken "
                                                    "from their peel fluxes).",
                                                    json_schema_extra={"allowed": "names from "
                                                                       "mmflow.sky.sources.CATALOG, or null"})
    flux_disc_fwhm: float = Field(0.8, gt=0, description="Radius of the flux disc, in PSF FWHMs at the source.")
    flux_annulus_fwhm: tuple[float, float] = Field((1.2, 2.0), description="Inner and outer radius of the "
                                                   "background annulus, in PSF FWHMs.",
                                                   json_schema_extra={"allowed": "[inner, outer] with "
                                                                      "flux_disc_fwhm <= inner < outer"})
    spectral_index: bool = Field(True, description="With >= 2 channels: T-T spectral index (beta, R^2) maps between "
                                 "the lowest and highest; with >= 3 a three-colour Mollweide scaled by nu^2.5.")
    spectral_index_radius_deg: float = Field(10.0, gt=0, le=90, description="Radius of the T-T regions.")
    spectral_index_nside: int = Field(32, description="nside of the beta and R^2 maps (the T-T inputs are "
                                      "averaged to twice this).",
                                      json_schema_extra={"allowed": "a power of two (1, 2, 4, ..., 2^29)"})
    astrometry: Optional[Literal["catalog"]] = Field(None, description="Astrometric registration against the "
                                                     "source catalogue (positions before and after a fitted "
                                                     "rotation; null: off).")
    astrometry_axis: Literal["any", "z"] = Field("any", description="Rotation fitted by the registration: any "
                                                 "small rotation, or about the pole only (an RA / clock shift).")

    @field_validator("spectral_index_nside")
    @classmethod
    def _si_nside(cls, v):
        return power_of_two(v)

    @field_validator("nside")
    @classmethod
    def _nside(cls, v):
        return power_of_two(v)


#: this stage's sections of the workflow schema
SECTIONS = {"products": ProductsConfig}
