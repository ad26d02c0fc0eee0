"""The science products' settings are refused before any work, naming the field, value and fix."""
import pytest

from mmflow.workflow.config.schema import load_config
from tests.workflow_helpers import DEMO, refused_problem

CASES = [
    (["products.flux_scale_sources=[Cyg A, 3C 2866]"], "products.flux_scale_sources", "not in the source catalogue",
     "did you mean '3C 286'?"),
    (["products.flux_annulus_fwhm=[0.5, 2.0]"], "products.flux_annulus_fwhm", "not an annulus outside the flux disc",
     "flux_disc_fwhm <= inner < outer"),
    (["products.flux_annulus_fwhm=[2.0, 1.5]"], "products.flux_annulus_fwhm", "not an annulus", "inner < outer"),
    (["products.spectral_index_nside=24"], "products.spectral_index_nside", "power of two", "use 16 or 32"),
    (["products.astrometry=nvss"], "products.astrometry", "'nvss' is not allowed", "catalog"),
    (["products.astrometry_axis=x"], "products.astrometry_axis", "'x' is not allowed", "any | z"),
]


@pytest.mark.parametrize("overrides, field, problem, fix", CASES, ids=[" ".join(c[0]) for c in CASES])
def test_bad_products_setting_is_refused_naming_field_value_and_fix(overrides, field, problem, fix):
    (_, _, prob, fx), _ = refused_problem(overrides, field)
    assert problem in prob, prob
    assert fix in fx, fx


def test_products_defaults_flux_scale_and_spectral_index_on_astrometry_off():
    p = load_config(DEMO, ["products.astrometry=catalog", "products.flux_scale_sources=[3C 286]"]).products
    assert p.flux_scale and p.spectral_index and p.astrometry == "catalog" and p.flux_scale_sources == ["3C 286"]
    assert load_config(DEMO, []).products.astrometry is None
