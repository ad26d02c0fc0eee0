"""The summary's CLEANed sources in ``products.frame``
(:func:`mmflow.workflow.stages.products.stokes.sources_in_frame`): positions moved and polarisation angles
turned so that they are still measured from north through east (IAU) in the new frame, checked against a
direction displaced along the source's angle and moved with it."""
import numpy as np
import pytest

from mmflow.conventions import radec_to_vec
from mmflow.sky.frames import rotation_matrix
from mmflow.workflow.stages.products.stokes import sources_in_frame

EPOCH_JD = 2461007.5  # 2025-12-01


def _north_east(r):
    n = np.array([0.0, 0.0, 1.0]) - r[2] * r
    n /= np.linalg.norm(n)
    return n, np.cross(n, r)


@pytest.mark.parametrize("frame", ["icrs", "galactic", "date"])
def test_sources_keep_their_polarisation_angle_from_north_through_east_in_the_output_frame(frame):
    """A short arc from each source along its angle (frame of date), moved to ``frame`` with the source,
    leaves it along the stated angle there (to 1e-4 deg); the position is the source's moved; the
    Stokes vector and the fractions are kept; a source not measured keeps its null angle."""
    entry = {"cycles": 3, "frame": "date", "sources": [
        {"ra_deg": ra, "dec_deg": dec, "angle_deg": chi, "stokes_jy": [1.0, 0.1, 0.2, 0.0], "linear_fraction": 0.22,
         "circular_fraction": 0.0, "cond": 2.0, "measured": True}
        for ra, dec, chi in ((10.0, 60.0, 30.0), (200.0, -20.0, -75.0), (300.0, 85.0, 89.0))]}
    entry["sources"].append(dict(entry["sources"][0], angle_deg=None, measured=False))
    out = sources_in_frame(entry, frame, EPOCH_JD)
    rot = np.eye(3) if frame == "date" else rotation_matrix("date", frame, EPOCH_JD)
    assert out["frame"] == frame and out["cycles"] == 3 and entry["sources"][0]["ra_deg"] == 10.0  # not changed
    for src, got in zip(entry["sources"], out["sources"]):
        r = radec_to_vec(np.deg2rad(src["ra_deg"]), np.deg2rad(src["dec_deg"]))
        r_out = rot @ r
        assert radec_to_vec(np.deg2rad(got["lon_deg"]), np.deg2rad(got["lat_deg"])) == pytest.approx(r_out, abs=1e-12)
        assert got["stokes_jy"] == src["stokes_jy"] and got["linear_fraction"] == src["linear_fraction"]
        if src["angle_deg"] is None:
            assert got["angle_deg"] is None
            continue
        n, e = _north_east(r)
        chi, step = np.deg2rad(src["angle_deg"]), 1e-5
        arc = rot @ (np.cos(step) * r + np.sin(step) * (np.cos(chi) * n + np.sin(chi) * e))
        n_o, e_o = _north_east(r_out)
        want = np.rad2deg(np.arctan2((arc - r_out) @ e_o, (arc - r_out) @ n_o))
        diff = (got["angle_deg"] - want + 90) % 180 - 90  # an angle of polarisation: modulo 180 deg
        assert abs(diff) < 1e-4 and -90 <= got["angle_deg"] < 90
