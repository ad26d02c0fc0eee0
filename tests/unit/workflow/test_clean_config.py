"""CLEAN's settings are refused before any work, naming the override, the field, the value and the fix."""

import pytest

from mmflow.workflow.config.schema import load_config
from tests.workflow_helpers import DEMO, refused_problem

ON = ["clean.enabled=true", "mmode.splits=[full, even, odd]"]

# (overrides, field, text in the problem, text in the fix)
CASES = [
    (["clean.gain=0"], "clean.gain", "0 is not allowed", "a number > 0, <= 1"),
    (["clean.gain=1.5"], "clean.gain", "1.5 is not allowed", "a number > 0, <= 1"),
    (["clean.peaks_per_cycle=0"], "clean.peaks_per_cycle", "0 is not allowed", "integer >= 1"),
    (["clean.min_separation_deg=0"], "clean.min_separation_deg", "0 is not allowed", "a number > 0"),
    (["clean.threshold_sigma=-3"], "clean.threshold_sigma", "-3 is not allowed", "a number > 0"),
    (["clean.max_cycles=0"], "clean.max_cycles", "0 is not allowed", "integer >= 1"),
    (["clean.stall_fraction=1"], "clean.stall_fraction", "1 is not allowed", ">= 0, < 1"),
    (["clean.psf_dec_step_deg=0"], "clean.psf_dec_step_deg", "0 is not allowed", "a number > 0"),
    (["clean.threshold_unit=mJy"], "clean.threshold_unit", "'mJy' is not allowed", "K | Jy/sr"),
    (["clean.nside=48"], "clean.nside", "power of two", "use 32 or 64"),
    (["clean.gian=0.1"], "clean.gian", "not an option of clean", "did you mean 'clean.gain'?"),
    # cross-field rules (only when CLEAN runs)
    # splits given without the jackknife halves (not given, clean.enabled brings [full, even, odd])
    (["clean.enabled=true", "mmode.splits=[full]"], "clean.threshold", "no even and odd halves",
     "mmode.splits=[full, even, odd]"),
    (ON + ["clean.min_separation_deg=2"], "clean.min_separation_deg", "closer than the resolution 180 / lmax = 2.5",
     "clean.min_separation_deg >= 2.5"),
    (ON + ["clean.highpass_lmin=72"], "clean.highpass_lmin", "not below mmode.lmax = 72", "highpass_lmin < 72"),
    (ON + ["clean.highpass_lmin=10", "clean.highpass_width=12"], "clean.highpass_width", "wider than",
     "clean.highpass_width <= 10"),
    (ON + ["imaging.method=moore_penrose"], "imaging.method", "Tikhonov operator", "imaging.method: tikhonov"),
]


@pytest.mark.parametrize("overrides, field, problem, fix", CASES, ids=[" ".join(c[0]) for c in CASES])
def test_bad_clean_setting_is_refused_naming_field_value_and_fix(overrides, field, problem, fix):
    (_, _, prob, fx), err = refused_problem(overrides, field, DEMO)
    assert problem in prob, prob
    assert fix in fx, fx
    assert "Fix:" in str(err)


@pytest.mark.parametrize("overrides", [
    ON,
    ["clean.enabled=true"],  # brings mmode.splits [full, even, odd] for the jackknife threshold
    ["clean.enabled=true", "clean.threshold=500"],  # an explicit threshold needs no jackknife
    ["clean.enabled=true", "clean.rel_threshold=1e-3"],
    ["clean.min_separation_deg=0.1"],  # CLEAN off: its settings are not checked against the rest
])
def test_good_clean_settings_load(overrides):
    cfg = load_config(DEMO, overrides)
    assert cfg.clean.gain == 0.15 and cfg.clean.peaks_per_cycle == 256 and cfg.clean.threshold_sigma == 3.0
