"""The quiet Sun in the simulate stage (``sky.sun``): issue 10's simulator item."""
import numpy as np
import zarr

from mmflow.sky.frames import source_enu
from mmflow.simulate.corrupt import _sun_vector_date, sun_points
from mmflow.workflow.engine.context import build_telescope
from mmflow.workflow.engine.runner import run_workflow
from tests.workflow_helpers import small_config

QUIET = dict(progress=False, log=lambda *a: None)


def test_sun_only_sky_peaks_at_its_transit_with_the_beam_weighted_disc_flux(tmp_path):
    """A sky of the Sun alone (no sources, no diffuse sky, no noise), one day in 2021 (not the
    default epoch): every autocorrelation equals the disc's flux through the beam at the Sun's
    apparent position, evaluated here directly (not through the drift-scan simulator); the day's
    largest autocorrelation is where the Sun is highest, and the flux has the positive spectral
    index (more at 50 MHz than at 40 MHz)."""
    jd = 2459390.5  # 2021-06-25, the Sun near its northernmost declination
    cfg = small_config(tmp_path / "run", "sky.sun=true", "sky.sources=[]", "sky.diffuse=false", "sky.noise=false",
                       "observation.freqs_mhz=[40.0, 50.0]", f"observation.epoch_jd={jd}",
                       "products.png=false", "imaging.lcurve=false", "run.keep=[vis.zarr]")
    run_workflow(cfg, **QUIET)
    vis = zarr.open_group(str(tmp_path / "run" / "vis.zarr"), mode="r")
    tel = build_telescope(cfg)
    lst, t = vis["lst"][:], vis["time_jd"][:]
    pairs = vis["pairs"][:]
    auto = np.flatnonzero(pairs[:, 0] == pairs[:, 1])[0]
    v = vis["vis"][:, auto, :, 0].real  # (time, freq)
    rows = np.arange(0, len(lst), 37)
    for fi, f in enumerate(tel.freqs_hz):
        for r in rows:
            chunk = slice(r // 256 * 256, min(len(lst), (r // 256 + 1) * 256))
            sun = sun_points(float(np.median(t[chunk])), float(f))  # the stage's position: the chunk's mid time
            enu = source_enu(tel, lst[r:r + 1], sun.vectors)[:, 0]  # (n_points, 3)
            expect = np.sum(tel.beam.power_enu(enu, float(f)) * sun.flux_jy * (enu[:, 2] > 0))
            assert abs(v[r, fi] - expect) <= 1e-4 * sun.flux_jy.sum() + 1e-6 * abs(expect), (r, fi, v[r, fi], expect)
    el = np.array(
        [source_enu(tel, lst[r : r + 1], _sun_vector_date(float(t[r]))[None])[0, 0, 2] for r in range(len(lst))]
    )
    assert abs(int(np.argmax(v[:, 0])) - int(np.argmax(el))) <= 1
    assert v[:, 1].max() > v[:, 0].max() > 0
