"""pyuvdata's first import pins the frames on the importing stack: imported in a thread
(``mmflow.import_thread``), a reader's ``UVData`` is freed when the caller drops it."""
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from mmflow.import_thread import import_in_thread

CHILD = textwrap.dedent('''
    import gc, sys, weakref
    sys.modules.pop("pyuvdata", None)
    assert "pyuvdata" not in sys.modules
    from mmflow.io.readers import read_metadata
    uv = read_metadata(sys.argv[1])
    ref = weakref.ref(uv)
    del uv
    gc.collect()
    print("alive" if ref() is not None else "freed")
''')


def test_a_file_read_in_the_first_import_is_freed(tmp_path):
    from astropy.coordinates import EarthLocation
    from pyuvdata import Telescope, UVData

    loc = EarthLocation.from_geodetic(-118.28, 37.24, 1183.0)
    tel = Telescope.new("t", loc, antenna_positions=np.array([[0.0, 0, 0], [10.0, 0, 0], [0, 12.0, 0]]),
                        antenna_names=["a", "b", "c"], antenna_numbers=[0, 1, 2], instrument="t", mount_type="fixed")
    uv = UVData.new(freq_array=np.array([50e6]), polarization_array=["xx"], times=2460000.5 + np.arange(3) / 8640,
                    telescope=tel, antpairs=[(0, 1), (0, 2), (1, 2)], do_blt_outer=True, integration_time=10.0,
                    channel_width=24e3, vis_units="Jy", time_axis_faster_than_bls=False,
                    data_array=np.ones((9, 1, 1), complex))
    path = tmp_path / "t.uvh5"
    uv.write_uvh5(str(path))
    out = subprocess.run([sys.executable, "-c", CHILD, str(path)], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "freed", out.stderr


def test_an_import_error_is_raised_in_the_caller():
    with pytest.raises(ModuleNotFoundError):
        import_in_thread("mmflow_no_such_module")
    assert import_in_thread("json").dumps([1]) == "[1]"
