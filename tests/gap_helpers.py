"""What the flagged-time tests share: a sky of bright and faint sources, a sin(elevation) beam file, and
flags written into a UVH5 file (tests/workflow/test_gap_prior_*.py)."""
import numpy as np

from tests.uvh5_helpers import gaussian_power_beamfits

RA = [30, 120, 200, 290, 250, 75, 160, 330, 10]
DEC = [60, 20, 45, 5, 75, 35, 65, 30, 15]
FLUX = [100.0, 80, 120, 5, 5, 5, 5, 5, 5]


def sin_elevation_beamfits(path, alpha=1.5):
    """A UVBeam power beam sin(elevation)^alpha on a 1 x 0.5 degree grid (mmflow's sin_elevation beam)."""
    uvb = gaussian_power_beamfits(path)
    uvb.data_array[:] = (np.clip(np.cos(uvb.axis2_array), 0, None) ** alpha)[None, None, None, :, None]
    uvb.write_beamfits(str(path), clobber=True)
    return uvb


def write_flagged(uv, path, bad):
    """``uv`` with every baseline of the integrations ``bad`` flagged, as one UVH5 file."""
    out = uv.copy()
    times = np.unique(out.time_array)
    out.flag_array[bad[np.searchsorted(times, out.time_array)]] = True
    out.write_uvh5(str(path), clobber=True, fix_autos=True)
    return path


def flag_blocks(rng, n_times, fraction=0.2, n_blocks=4):
    """``fraction`` of ``n_times`` integrations flagged in ``n_blocks`` blocks, one at random in each part."""
    bad = np.zeros(n_times, bool)
    seg, length = n_times // n_blocks, int(fraction / n_blocks * n_times)
    for k in range(n_blocks):
        s = k * seg + rng.integers(0, seg - length)
        bad[s:s + length] = True
    return bad
