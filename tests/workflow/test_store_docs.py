"""docs/stores.md is generated from the declared stores (mmflow/io/run_stores.py) and kept in sync."""
import os

from mmflow.calibrate import peel as peel_kernel
from mmflow.cli import main
from mmflow.io import calibration_stores, run_stores
from mmflow.io.store_docs import pattern, reference_stores, store_builders, stores_markdown, undocumented
from mmflow.workflow.pipeline import PIPELINE
from tests.workflow_helpers import ROOT

STORES_MD = os.path.join(ROOT, "docs", "stores.md")


def test_docs_stores_page_matches_declarations():
    with open(STORES_MD) as fh:
        assert fh.read() == stores_markdown(PIPELINE.lifetimes()), \
            "regenerate docs/stores.md with `make docs` (`mmflow stores show`)"


def test_every_store_builder_is_on_the_page():
    builders = store_builders()
    assert {b.__name__ for b in builders} >= {
        "vis_store", "mmodes_store", "partials_store", "normal_store", "alm_store", "transfer_store", "gains_store",
        "peel_store", "models_store", "terrestrial_store", "clean_store"}
    references = [b for b, _ in reference_stores()]
    assert len(references) == len(builders) and set(references) == set(builders)  # one reference call each
    with open(STORES_MD) as fh:
        doc = fh.read()
    for builder, kwargs in reference_stores():
        spec = builder(**kwargs)
        assert f"\n## {spec.path}\n" in doc and f"`{builder.__name__}(" in doc
        section = doc.split(f"\n## {spec.path}\n")[1].split("\n## ")[0]
        for a in spec.arrays:
            assert f"| `{pattern(a.name)}`" in section, (spec.path, a.name)


def test_every_store_array_and_dimension_has_a_meaning():
    specs = [b(**kw) for b, kw in reference_stores()]
    assert undocumented(specs) == []
    used = {d for s in specs for a in s.arrays for d in a.dims}
    assert used == set(run_stores.DIMENSIONS)  # every dimension described, no description left over


def test_chunk_rules_name_the_parameters():
    doc = stores_markdown()
    vis = doc.split("\n## vis.zarr\n")[1].split("\n## ")[0]
    # one channel per chunk: a task of one channel reads it alone
    assert "| `vis` | (time, baseline, freq, pol) | (1000, 36, 2, 2) | (time_chunk, baseline_chunk, 1, all) |" in vis
    alm = doc.split("\n## alm.zarr\n")[1].split("\n## ")[0]
    assert "| `alm` | (split, freq, m, l) | (3, 2, 41, 41) | (all, 1, m_block, all) | complex128 |" in alm
    assert "| `f{F}/gram_b{M0}` (10 arrays) | (group, m, triangle) | (4, 10, 861) | (1, all, all) |" in doc


def test_peel_mode_codes_are_the_kernels():
    codes = {"skip": peel_kernel.SKIP, "peel": peel_kernel.PEEL, "subtract": peel_kernel.SUBTRACT,
             "model": peel_kernel.MODEL}
    assert {name: i for i, name in enumerate(calibration_stores.PEEL_MODES)} == codes
    assert "0 skip, 1 peel, 2 subtract, 3 model" in stores_markdown()


def test_cli_stores_show_prints_the_page(capsys):
    assert main(["stores", "show"]) == 0
    assert capsys.readouterr().out == stores_markdown(PIPELINE.lifetimes())
