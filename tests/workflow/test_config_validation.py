"""Every bad value is refused by load_config, before any work, with a message that names it.

Each case checks the four parts of the message: where the value came from (file and line, or
the command-line override), the field, the bad value and the fix.
"""
import inspect
import os

import numpy as np
import pytest
import yaml

from mmflow.errors import InputError
from mmflow.workflow.config.schema import BEAM_PARAMS, WorkflowConfig, load_config, schema_yaml
from mmflow.workflow.config.errors import ConfigError
from tests.workflow_helpers import ROOT, refused_problem

DEMO = os.path.join(ROOT, "workflows", "demo.yaml")

# (override, field, text in the problem, text in the fix)
OVERRIDE_CASES = [
    ("imaging.epss=0.001", "imaging.epss", "not an option of imaging", "did you mean 'imaging.eps'?"),
    ("mmode.eps=0.1", "mmode.eps", "not an option of mmode", "'imaging.eps'"),
    ("imagng.eps=0.1", "imagng", "not an option of the top level", "did you mean 'imaging'?"),
    ("mmode.lmax=-1", "mmode.lmax", "-1 is not allowed", "integer >= 1"),
    ("mmode.lmax=0", "mmode.lmax", "0 is not allowed", "integer >= 1"),
    ("mmode.lmax=abc", "mmode.lmax", "'abc' is not allowed", "integer >= 1"),
    ("imaging.eps=0", "imaging.eps", "0 is not allowed", "a number > 0"),
    ("imaging.eps=-0.01", "imaging.eps", "-0.01 is not allowed", "a number > 0"),
    ("imaging.eps=.nan", "imaging.eps", "NaN is not allowed (input should be a finite number)", "a number > 0"),
    ("products.nside=6", "products.nside", "6: HEALPix nside must be a power of two", "use 4 or 8"),
    ("products.nside=0", "products.nside", "power of two", "use 1 or 2"),
    ("transfer.m_block=0", "transfer.m_block", "0 is not allowed", "integer >= 1"),
    ("transfer.baseline_chunk=0", "transfer.baseline_chunk", "0 is not allowed", "integer >= 1"),
    ("mmode.baseline_chunk=0", "mmode.baseline_chunk", "0 is not allowed", "integer >= 1"),
    ("mmode.mmax=73", "mmode.mmax", "73: larger than mmode.lmax = 72", "mmode.mmax <= 72"),
    ("observation.integration_s=0", "observation.integration_s", "0 is not allowed", "a number > 0"),
    ("observation.integration_s=-13", "observation.integration_s", "-13 is not allowed", "a number > 0"),
    ("cluster.memory_limit=abc", "cluster.memory_limit", "'abc': not a memory size", "'4GiB'"),
    ("cluster.memory_limit=-1", "cluster.memory_limit", "must be positive", "'auto'"),
    ("imaging.method=prior", "imaging.prior_map", "method 'prior' needs a prior map", "imaging.prior_map"),
    ("imaging.prior_map=/nonexistent/prior.fits", "imaging.prior_map", "file not found", "HEALPix FITS"),
    ("telescope.lat_deg=91", "telescope.lat_deg", "91 is not allowed", ">= -90, <= 90"),
    ("telescope.lat_deg=-100", "telescope.lat_deg", "-100 is not allowed", ">= -90, <= 90"),
    ("telescope.radius_m=1", "telescope.radius_m", "keeps no antennas", "telescope.radius_m >= "),
    ("telescope.stands=[LWA-001, LWA-999]", "telescope.stands", "unknown stand names ['LWA-999']", "names"),
    ("telescope.stands=[]", "telescope.stands", "[] is not allowed", "at least 2"),
    ("telescope.max_antennas=1", "telescope.max_antennas", "1 is not allowed", "integer >= 2"),
    ("telescope.max_antennas=0", "telescope.max_antennas", "0 is not allowed", "integer >= 2"),
    ("mmode.min_coverage=1.5", "mmode.min_coverage", "1.5 is not allowed", ">= 0, <= 1"),
    ("mmode.min_coverage=-0.1", "mmode.min_coverage", "-0.1 is not allowed", ">= 0, <= 1"),
    ("beam={type: gaussian, fwhm_deg: -30}", "beam.fwhm_deg", "-30 is not allowed", "beam.fwhm_deg to a number > 0"),
    ("beam={type: gaussian, fwhm: 30}", "beam.fwhm", "not a parameter of beam type 'gaussian'", "'beam.fwhm_deg'"),
    ("beam.alpha=0", "beam.alpha", "0 is not allowed", "a number > 0"),
    ("beam={type: gausian}", "beam.type", "'gausian' is not allowed", "did you mean 'gaussian'?"),
    ("beam={type: zernike, freqs_hz: [40.0e+6], coeffs: [[1, 0]]}", "beam", "9", "9 coefficients"),
    ("beam={type: zernike, freqs_hz: [30.0e+6], coeffs: [[1, 0, 0, 0, 0, 0, 0, 0, 0]]}", "observation.freqs_mhz",
     "40.000 MHz outside", "covering every channel"),
    ("beam={type: pyuvdata}", "beam", "exactly one of 'file' and 'class'", "beam={type: pyuvdata, file"),
    ("beam={type: pyuvdata, file: /nonexistent/beam.fits}", "beam.file", "file not found", "pyuvdata"),
    ("telescope.layout_file=/nonexistent/layout.txt", "telescope.preset", "and layout_file", "preset: null"),
    ("run.directory=''", "run.directory", "the run directory is empty", "run.directory=runs/"),
    ("run.directory=' '", "run.directory", "the run directory is empty", "run.directory=runs/"),
    ("cluster.n_workers=0", "cluster.n_workers", "0 is not allowed", "integer >= 1"),
    ("cluster.n_workers=-2", "cluster.n_workers", "-2 is not allowed", "integer >= 1"),
    ("cluster.threads_per_worker=0", "cluster.threads_per_worker", "0 is not allowed", "integer >= 1"),
    ("cluster.worker_wait_s=0", "cluster.worker_wait_s", "0 is not allowed", "a number > 0"),
    ("cluster.dashboard_address=0.0.0.0:8787", "cluster.dashboard_address", "listens beyond this machine",
     "cluster.expose: true"),
    ("cluster.dashboard_address=localhost", "cluster.dashboard_address", "not '[host]:port'", "':8787'"),
    ("input.nonfinite=drop", "input.nonfinite", "'drop' is not allowed", "error | flag"),
    ("products.frame=galatic", "products.frame", "'galatic' is not allowed", "did you mean 'galactic'?"),
    ("sky.sources=['Cyg B']", "sky.sources", "'Cyg B': not in the source catalogue", "did you mean 'Cyg A'?"),
    ("mmode.n_bins=100", "mmode.n_bins", "too few sidereal bins", ">= 145"),
    ("observation.integration_s=700", "observation.integration_s", "123 integrations per sidereal day",
     "integration_s <= 594.2"),
    ("observation.n_integrations=100", "observation.n_integrations", "covers 1.5% of the sidereal day",
     "at least 4640 integrations"),
    ("telescope.include_autos=false", "sky.noise", "autocorrelations", "sky.noise: false"),
    ("observation.freqs_mhz=[]", "observation.freqs_mhz", "[] is not allowed", "numbers > 0"),
    ("observation.freqs_mhz=[40, -1]", "observation.freqs_mhz", "non-positive frequencies [-1.0]", "all > 0"),
    ("mmode=5", "mmode", "5 is not a section", "mmode: {key: value}"),
]


@pytest.mark.parametrize("override, field, problem, fix", OVERRIDE_CASES, ids=[c[0] for c in OVERRIDE_CASES])
def test_bad_override_names_override_field_value_and_fix(override, field, problem, fix):
    (what, _, prob, fx), err = refused_problem([override], field, DEMO)
    assert problem in prob, prob
    assert fix in fx, fx
    # the override that set the value is named (cross-field rules may name the other field's origin)
    assert "command-line override" in what or "demo.yaml" in what
    assert f"'{field}'" in str(err) and "Fix:" in str(err)


def test_origin_is_the_override_that_set_the_value():
    err = pytest.raises(InputError, load_config, DEMO, ["mmode.lmax=0"]).value
    assert err.what == "command-line override 'mmode.lmax=0'"
    assert str(err).startswith("command-line override 'mmode.lmax=0': field 'mmode.lmax': 0 is not allowed")


def _write(tmp_path, text, name="w.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_bad_value_in_a_file_names_the_file_and_line(tmp_path):
    p = _write(tmp_path, "run: {directory: out}\nmmode:\n  baseline_chunk: 64\n  lmax: -1\n")
    err = pytest.raises(InputError, load_config, p).value
    assert err.what == f"{p}, line 4" and err.field == "mmode.lmax" and "-1 is not allowed" in err.problem


def test_every_problem_is_reported_at_once(tmp_path):
    p = _write(tmp_path, "mmode: {lmax: 0, baseline_chunk: 0}\nimaging: {eps: -1}\ncluster: {n_workers: 0}\n")
    err = pytest.raises(ConfigError, load_config, p).value
    assert {f for _, f, _, _ in err.problems} == {"mmode.lmax", "mmode.baseline_chunk", "imaging.eps",
                                                   "cluster.n_workers"}
    assert all(w == f"{p}, line {1 if f.startswith('mmode') else 2 if f.startswith('imaging') else 3}"
               for w, f, _, _ in err.problems)
    assert len(str(err).splitlines()) == 4


@pytest.mark.parametrize("text, line, words", [
    ("mmode:\n  lmax: 64\n imaging: 1\n", 3, "expected <block end>"),
    ("mmode:\n\tlmax: 64\n", 2, "'\\t' that cannot start any token"),
    ("mmode: {lmax: 64\n", 2, "expected ',' or '}'"),
])
def test_yaml_syntax_error_in_a_file_names_file_and_line(tmp_path, text, line, words):
    p = _write(tmp_path, text)
    err = pytest.raises(InputError, load_config, p).value
    assert err.what.startswith(f"{p}, line {line}") and err.field == "YAML syntax"
    assert words in err.problem and "indented with spaces" in err.fix


def test_yaml_syntax_error_in_an_override_names_the_override():
    err = pytest.raises(InputError, load_config, DEMO, ["observation.freqs_mhz=[40, 50"]).value
    assert err.what.startswith("command-line override 'observation.freqs_mhz=[40, 50'")
    assert err.field == "YAML syntax"


@pytest.mark.parametrize("text", ["- mmode\n- imaging\n", "just a string\n", "42\n"])
def test_top_level_must_be_a_mapping(tmp_path, text):
    p = _write(tmp_path, text)
    err = pytest.raises(InputError, load_config, p).value
    assert err.what == str(p) and err.field == "(top level)" and "not a mapping of sections" in err.problem


def _layout(tmp_path, rows):
    p = tmp_path / "layout.txt"
    p.write_text("".join(f"{n} {e} {nn} 0\n" for n, e, nn in rows))
    return p


SITE = ["telescope.lat_deg=37.2", "telescope.lon_deg=-118.3"]


@pytest.mark.parametrize("rows, problem", [
    ([("A", 0, 0)], "keeps one antenna"),
    ([("A", 0, 0), ("A", 10, 0), ("B", 0, 10)], "duplicate names ['A']"),
    ([("A", 0, 0), ("B", 5, 5), ("C", 5, 5)], "antennas at the same position [['B', 'C']]"),
])
def test_layout_file_with_one_antenna_or_duplicates_is_refused(tmp_path, rows, problem):
    lay = _layout(tmp_path, rows)
    err = pytest.raises(InputError, load_config, DEMO,
                        ["telescope={layout_file: %s, lat_deg: 37.2, lon_deg: -118.3}" % lay]).value
    assert problem in str(err) and "telescope" in err.field


def test_layout_file_alone_replaces_the_default_preset_and_validates(tmp_path):
    lay = _layout(tmp_path, [("A", 0, 0), ("B", 10, 0), ("C", 0, 12)])
    cfg = load_config(None, [f"telescope.layout_file={lay}", *SITE])
    assert cfg.telescope.preset is None and cfg.telescope.layout_file == str(lay)


@pytest.mark.parametrize("written", ["~/arrays/layout.txt", "$MMFLOW_TEST_ARRAYS/layout.txt",
                                     "${HOME}/arrays/layout.txt"])
def test_a_layout_file_under_home_or_a_variable_is_read_by_the_check_and_the_run_alike(tmp_path, monkeypatch, written):
    """``~`` and variables expand once, when the configuration is read: the checks and the telescope the
    stages build read the same file (before, only the check expanded ``~`` and the run died on it)."""
    from mmflow.workflow.engine.context import build_telescope

    (tmp_path / "arrays").mkdir()
    lay = _layout(tmp_path / "arrays", [("A", 0, 0), ("B", 10, 0), ("C", 0, 12)])
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("MMFLOW_TEST_ARRAYS", str(tmp_path / "arrays"))
    cfg = load_config(None, [f"telescope.layout_file={written}", *SITE])
    assert cfg.telescope.layout_file == str(lay)
    tel = build_telescope(cfg)
    assert list(tel.layout.names) == ["A", "B", "C"]
    np.testing.assert_allclose(tel.layout.enu[1] - tel.layout.enu[0], [10, 0, 0], atol=1e-9)


def test_preset_and_layout_file_together_are_refused(tmp_path):
    lay = _layout(tmp_path, [("A", 0, 0), ("B", 10, 0)])
    err = pytest.raises(InputError, load_config, None, ["telescope.preset=full", f"telescope.layout_file={lay}",
                                                        *SITE]).value
    assert err.field == "telescope.preset" and "both given" in err.problem
    assert err.what == "command-line override 'telescope.preset=full'"


def test_site_of_a_preset_cannot_be_overridden():
    err = pytest.raises(InputError, load_config, DEMO, ["telescope.lat_deg=10"]).value
    assert err.field == "telescope.lat_deg" and "only used with layout_file" in err.problem


def test_empty_selection_is_named_before_the_simulate_stage(tmp_path):
    """Previously reported by the simulate stage as 'thermal noise needs autocorrelations'."""
    err = pytest.raises(InputError, load_config, DEMO, ["telescope.radius_m=0.5"]).value
    assert "keeps no antennas" in err.problem and "autocorrelations" not in str(err)


def test_run_directory_that_is_a_file(tmp_path):
    f = _write(tmp_path, "x", "afile")
    err = pytest.raises(InputError, load_config, DEMO, [f"run.directory={f}"]).value
    assert err.field == "run.directory" and "is a file" in err.problem


def test_a_failed_validation_writes_nothing(tmp_path):
    from mmflow.cli import main

    run_dir = tmp_path / "never"
    assert main(["run", DEMO, f"run.directory={run_dir}", "mmode.lmax=0", "--no-progress"]) == 2
    assert not run_dir.exists() and list(tmp_path.iterdir()) == []


def test_valid_values_pass_and_keep_their_meaning():
    cfg = load_config(DEMO, ["cluster.memory_limit=0.5", "products.nside=64", "mmode.mmax=32",
                             "beam={type: gaussian, fwhm_deg: 30, ref_freq_hz: 40.0e+6}", "cluster.memory_limit=4GiB"])
    assert cfg.cluster.memory_limit == "4GiB" and cfg.products.nside == 64 and cfg.mmode.mmax == 32
    assert cfg.beam.model_dump() == {"type": "gaussian", "fwhm_deg": 30, "ref_freq_hz": 40e6}
    assert load_config(DEMO, ["cluster.memory_limit=auto"]).cluster.memory_limit == "auto"
    assert load_config(DEMO, ["cluster.memory_limit=0.25"]).cluster.memory_limit == "0.25"


def test_beam_parameter_models_match_the_beam_classes():
    """The documented defaults are the ones make_beam uses (no second source of truth drifts)."""
    from mmflow.telescope import beams

    for kind, cls in (("sin_elevation", beams.SinElevationBeam), ("gaussian", beams.GaussianBeam),
                      ("zernike", beams.ZernikeBeam)):
        sig = inspect.signature(cls.__init__).parameters
        model = BEAM_PARAMS[kind].model_fields
        assert set(model) == set(sig) - {"self"}, kind
        for name, f in model.items():
            if not f.is_required():
                assert sig[name].default == f.default, (kind, name)
    sig = inspect.signature(beams.PyUVDataBeam.__init__).parameters
    for name in ("normalize", "lmax_hint"):
        assert BEAM_PARAMS["pyuvdata"].model_fields[name].default == sig[name].default
    from mmflow.telescope.jones import ShortDipoleJones

    sig = inspect.signature(ShortDipoleJones.__init__).parameters
    model = BEAM_PARAMS["short_dipole"].model_fields
    assert set(model) == set(sig) - {"self"}
    for name, f in model.items():
        assert sig[name].default == f.default, name


def test_config_show_lists_allowed_values_and_every_beam_type_and_round_trips(tmp_path):
    text = schema_yaml()
    for words in ("eps: 0.01", "[a number > 0]", "one of tikhonov | min_variance", "fwhm_deg: 60.0",
                  "type gaussian", "type zernike", "type pyuvdata", "class: null", "a power of two",
                  "expose: false", "worker_wait_s: 300.0", "nonfinite: error  # Unflagged NaN/inf"):
        assert words in text, words
    for line in text.splitlines():  # every option line states its allowed values
        if not line.strip().startswith("#") and "  # " in line and not line.split("  # ")[0].endswith(":"):
            assert line.rstrip().endswith("]"), line
    cfg = load_config(_write(tmp_path, text))
    default = WorkflowConfig()
    assert cfg.model_dump(exclude={"beam"}) == default.model_dump(exclude={"beam"})
    assert cfg.beam.model_dump() == {"type": "sin_elevation", "alpha": 1.5}
    assert yaml.safe_load(text)["mmode"]["lmax"] == 64


def test_changing_the_beam_type_alone_names_the_leftover_parameter():
    err = pytest.raises(InputError, load_config, DEMO, ["beam.type=gaussian"]).value
    assert err.field == "beam.alpha" and err.what.endswith("demo.yaml, line 13")
    assert "belongs to beam type 'sin_elevation'" in err.fix and "beam={type: gaussian, ...}" in err.fix


@pytest.mark.parametrize("override, fix", [("mmode.splits=[even, full]", "[full, even, odd]"),
                                           ("mmode.splits=[full, odd, odd]", "[full, even, odd]"),
                                           ("transfer.groups=0", "integer >= 1")])
def test_splits_and_groups(override, fix):
    err = pytest.raises(InputError, load_config, DEMO, [override]).value
    assert err.field == override.split("=")[0] and fix in err.fix


def test_options_and_overrides_in_any_order(tmp_path, capsys):
    """`mmflow run wf.yaml --no-progress key=value`: the override after the option is applied (here a bad
    value, refused by validation with exit 2 and the field named), not rejected by the argument parser."""
    from mmflow.cli import main

    run_dir = tmp_path / "never"
    assert main(["run", DEMO, "--no-progress", f"run.directory={run_dir}", "mmode.lmax=0"]) == 2
    assert "mmode.lmax" in capsys.readouterr().err and not run_dir.exists()
    with pytest.raises(SystemExit):  # an unknown option is still an error
        main(["run", DEMO, "--no-progress", "--bogus"])
    with pytest.raises(SystemExit):  # and so are stray words for a command without overrides
        main(["status", str(tmp_path), "extra=1"])


def test_clean_brings_the_splits_it_needs():
    """clean.enabled alone gets mmode.splits [full, even, odd] (its jackknife threshold); splits the user
    gives are kept, and without even/odd or a threshold they are still refused."""
    assert load_config(DEMO, ["clean.enabled=true"]).mmode.splits == ["full", "even", "odd"]
    assert load_config(DEMO).mmode.splits == ["full"]
    assert load_config(DEMO, ["clean.enabled=true", "mmode.splits=[full, odd, even]"]).mmode.splits[1] == "odd"
    err = pytest.raises(InputError, load_config, DEMO, ["clean.enabled=true", "mmode.splits=[full]"]).value
    assert "clean.threshold" in str(err)


def test_even_odd_splits_with_an_odd_number_of_bins_are_refused_before_work():
    """Found at the m-mode stage after simulate and calibrate had run; now refused by the configuration."""
    err = pytest.raises(InputError, load_config, DEMO, ["mmode.splits=[full, even, odd]", "mmode.n_bins=829"]).value
    assert "mmode.n_bins" in str(err) and "830" in str(err)
    assert load_config(DEMO, ["mmode.splits=[full, even, odd]", "mmode.n_bins=830"]).mmode.n_bins == 830


@pytest.mark.parametrize("measure, problem, fix", [
    ("[Vir A]", "not among calibrate.screen_sources and calibrate.sources", "list it in both"),
    ("[Cyg A, Cas A]", "none is left to set the flux scale", "out of calibrate.measure_flux"),
])
def test_measured_fluxes_must_be_screened_and_leave_a_flux_scale(measure, problem, fix):
    (_, _, prob, fx), _ = refused_problem(["calibrate.enabled=true", f"calibrate.measure_flux={measure}"],
                                          "calibrate.measure_flux", DEMO)
    assert problem in prob and fix in fx, (prob, fx)
