"""Channel selection and averaging at ingest against pyuvdata's ``select(frequencies=...)`` and
``frequency_average`` on the real OVRO-LWA MeasurementSet (109 channels of 24 kHz), and files that hold
one subband each grouped by frequency (the HERA drift scan split per subband and per integration)."""
import tarfile
from pathlib import Path

import numpy as np
import pytest

from mmflow.errors import InputError
from tests.rawfile_helpers import ingest, pyuvdata_reference
from tests.workflow_helpers import ROOT

DATA = Path(ROOT) / "tests" / "data"
OVRO = "2018-03-21-01_26_33_0004384620257280_000000_downselected.ms"
HERA = DATA / "zen.2458661.23480.HH.uvh5"
EPS = 4 * np.finfo(np.float32).eps


@pytest.fixture(scope="module")
def ovro(tmp_path_factory):
    root = tmp_path_factory.mktemp("ovro")
    with tarfile.open(DATA / f"{OVRO}.tar.gz") as tar:
        tar.extractall(root, filter="data")
    return root / OVRO


def _freqs_arg(mhz):
    return "observation.freqs_mhz=[" + ", ".join(repr(float(f)) for f in mhz) + "]"


def _same(g, ref):
    uv, ants, pairs, vis, w = ref
    np.testing.assert_allclose(g["freqs_hz"][:], uv.freq_array.ravel(), rtol=1e-12)
    np.testing.assert_array_equal(g["pairs"][:], pairs)
    np.testing.assert_allclose(g["weights"][:], w, rtol=1e-6, atol=0)
    np.testing.assert_allclose(g["vis"][:], vis, rtol=0, atol=EPS * np.abs(vis).max())


def test_nearest_channels_equal_pyuvdata_select(ovro, tmp_path):
    want = [27.5, 28.81, 29.9]  # MHz, within half a channel of a file channel each
    g = ingest(ovro, tmp_path / "run", _freqs_arg(want))
    file_f = np.arange(109) * 24e3 + 27.384e6
    nearest = [file_f[np.argmin(np.abs(file_f - f * 1e6))] for f in want]
    _same(g, pyuvdata_reference(ovro, lambda uv: uv.select(frequencies=nearest)))
    assert g.attrs["channel_width_hz"] == 24e3


def test_average_around_each_frequency_equals_pyuvdata_frequency_average_with_flags(ovro, tmp_path):
    """Four channels around each frequency (k - 1 .. k + 2), with random flags, one block wholly flagged
    on one baseline, and random nsample weights: pyuvdata's frequency_average(chan_map=...)."""
    from pyuvdata import UVData

    uv = UVData.from_file(str(ovro))
    rng = np.random.default_rng(7)
    uv.flag_array = rng.random(uv.flag_array.shape) < 0.25
    uv.flag_array[3, 50:54] = True
    uv.nsample_array = rng.uniform(0.5, 1.0, uv.nsample_array.shape).astype(np.float32)
    path = tmp_path / "flagged.uvh5"
    uv.write_uvh5(str(path))
    want = [28.593, 29.4]
    g = ingest(path, tmp_path / "run", _freqs_arg(want), "input.average_channels=4")
    chan_map = np.full(109, -1)
    for o, f in enumerate(want):
        k = int(np.argmin(np.abs(uv.freq_array - f * 1e6)))
        chan_map[k - 1:k + 3] = o

    def average(u):
        u.frequency_average(chan_map=chan_map)

    ref = pyuvdata_reference(path, average)
    _same(g, ref)
    assert g.attrs["channel_width_hz"] == 4 * 24e3
    assert (ref[4] == 0).any() and (g["weights"][:] == 0).any()  # the wholly flagged block weighs 0


def test_frequencies_beyond_half_a_channel_refused_naming_the_nearest(ovro, tmp_path):
    """Inside the band every frequency is within half a 24 kHz channel of one; outside it is not."""
    with pytest.raises(InputError, match=r"observation.freqs_mhz.*35 MHz.*nearest channels are at 29.952000, "
                                         r"29.976000 MHz"):
        ingest(ovro, tmp_path / "r1", _freqs_arg([35.0]))
    with pytest.raises(InputError, match=r"27.371 MHz is 13.0 kHz from the nearest.*27.384000, 27.408000 MHz"):
        ingest(ovro, tmp_path / "r2", _freqs_arg([27.371]))
    ingest(ovro, tmp_path / "r2b", _freqs_arg([27.373]))  # 11 kHz below the lowest channel: that channel
    with pytest.raises(InputError, match=r"input.average_channels.*200 channels"):
        ingest(ovro, tmp_path / "r3", _freqs_arg([28.0]), "input.average_channels=200")


def test_one_file_per_subband_per_integration_grouped_by_frequency(tmp_path):
    """The HERA scan (20 integrations, 4 channels) written as 2 subbands x 20 integrations = 40 files
    ingests to the store of the whole file, with every channel or a selection from both subbands."""
    from pyuvdata import UVData

    whole = UVData.from_file(str(HERA))
    d = tmp_path / "split"
    d.mkdir()
    for k, t in enumerate(np.unique(whole.time_array)):
        for s, chans in enumerate(([0, 1], [2, 3])):
            whole.select(times=[t], freq_chans=chans, inplace=False).write_uvh5(str(d / f"t{k:02d}_sb{s}.uvh5"))
    ref = ingest(HERA, tmp_path / "whole")
    got = ingest(d / "*.uvh5", tmp_path / "split_run")
    for name in ("freqs_hz", "pairs", "weights", "vis", "lst"):
        np.testing.assert_array_equal(got[name][:], ref[name][:], err_msg=name)
    f = whole.freq_array.ravel()
    want = [f[1] / 1e6, f[2] / 1e6]
    sel = ingest(d / "*.uvh5", tmp_path / "sel", _freqs_arg(want))
    np.testing.assert_array_equal(sel["vis"][:], ref["vis"][:, :, 1:3])
    np.testing.assert_array_equal(sel["weights"][:], ref["weights"][:, :, 1:3])
