"""``mmflow bench clean`` times the major cycle through the clean stage's own functions: its
stage-form cycle (factors read back from a zarr array per m block) equals the in-memory cycle."""
import numpy as np

from mmflow.bench import clean as bc
from mmflow.imaging import clean, psf
from mmflow.sky.diffuse import band_limited_random_alm


def test_stage_form_cycle_equals_the_in_memory_cycle(tmp_path):
    lmax, nside = 40, 32
    ops, _, _, _ = bc.build_operators(lmax, 1e-2, l_scale=bc.L_SCALE * lmax)
    dirty = psf.observe_alm(ops, 50 * band_limited_random_alm(lmax, seed=2), lmax)
    table = psf.psf_table(ops, lmax, np.deg2rad([-30.0, 0.0, 45.0, 90.0]))
    mask = clean.observed_mask(nside, np.deg2rad(-52.8))
    out = bc.stage_cycle(ops, lambda m: bc.synthetic_gram(m, lmax, bc.L_SCALE * lmax), dirty, table, mask, nside,
                         lmax, 16, workdir=tmp_path)
    assert out["max_rel_difference_to_in_memory_cycle"] == 0.0
    assert out["n_blocks"] == 3 and out["components"] > 0
    parts = out["block_task_seconds_summed"]
    assert set(parts) == {"read_factors_s", "operators_s", "components_s", "observe_s"}
    assert out["seconds"] == out["driver_s"] + out["blocks_wall_s"] and out["driver_s"] >= out["synthesis_s"]
    assert not any(tmp_path.iterdir())  # the factor store is removed
