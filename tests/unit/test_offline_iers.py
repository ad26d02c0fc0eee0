"""The parsed IERS table kept in mmflow's cache folder: the same table as astropy's own parse, a
damaged cache file replaced, an unwritable folder harmless (mmflow.offline)."""
import subprocess
import sys

import numpy as np
from astropy.utils import iers

from mmflow import offline

ROTATE = ("import mmflow; from mmflow.sky.frames import rotation_matrix; "
          "print(repr(rotation_matrix('icrs', 'date', 2457802.0).tolist()))")


def _columns_equal(a, b):
    for c in a.colnames:
        x, y = a[c], b[c]
        if not np.array_equal(np.asarray(x), np.asarray(y), equal_nan=x.dtype.kind == "f"):
            return False
        if not np.array_equal(np.ma.getmaskarray(x), np.ma.getmaskarray(y)):
            return False
    return a.colnames == b.colnames


def _fresh_read(monkeypatch, cache):
    monkeypatch.setenv("MMFLOW_CACHE_DIR", str(cache))
    return iers.IERS_Auto.read()


def test_cached_table_equals_astropys_parse_and_is_written_once(tmp_path, monkeypatch):
    astropy_read = iers.IERS_Auto.read.__func__.astropy_read
    parsed = astropy_read(iers.IERS_Auto)
    first = _fresh_read(monkeypatch, tmp_path)  # parses and writes the cache file
    files = list(tmp_path.glob("iers-auto-*.pickle"))
    assert len(files) == 1 and files[0].stat().st_size > 1_000_000
    second = _fresh_read(monkeypatch, tmp_path)  # from the file
    assert second is not first and _columns_equal(parsed, first) and _columns_equal(parsed, second)
    assert second.meta == parsed.meta and len(list(tmp_path.iterdir())) == 1


def test_damaged_cache_file_is_parsed_again_and_replaced(tmp_path, monkeypatch):
    monkeypatch.setenv("MMFLOW_CACHE_DIR", str(tmp_path))
    path = offline._iers_cache_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x80\x05 truncated by a kill")
    table = iers.IERS_Auto.read()
    assert isinstance(table, iers.IERS_Auto) and len(table) > 10_000
    assert path.stat().st_size > 1_000_000  # replaced by a whole table


def test_processes_give_the_same_rotation_with_and_without_the_cache(tmp_path):
    """A process that parses (empty cache, unwritable folder) and one that loads the cache file give
    the same frame rotation to the last bit."""
    import os

    env = dict(os.environ, MMFLOW_CACHE_DIR=str(tmp_path / "cache"))
    blocked = tmp_path / "file"
    blocked.write_text("a file where the folder would be: nothing can be cached")
    runs = [subprocess.run([sys.executable, "-c", ROTATE], env=e, capture_output=True, text=True, check=True).stdout
            for e in (dict(env, MMFLOW_CACHE_DIR=str(blocked / "sub")), env, env)]
    assert runs[0] == runs[1] == runs[2] and runs[0].startswith("[[0.99999")
    assert len(list((tmp_path / "cache").glob("iers-auto-*.pickle"))) == 1


def test_no_home_folder_means_no_cache_not_a_failure(monkeypatch):
    """A process without a home folder (HOME unset in some containers) parses as astropy alone would."""
    from pathlib import Path

    def no_home():
        raise RuntimeError("Could not determine home directory.")

    monkeypatch.delenv("MMFLOW_CACHE_DIR", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setattr(Path, "home", staticmethod(no_home))
    table = iers.IERS_Auto.read()
    assert isinstance(table, iers.IERS_Auto) and len(table) > 10_000


def test_compiled_kernels_import_and_run_from_a_read_only_installation(tmp_path):
    """A read-only installation without a writable home: numba finds no folder for the kernels' cache
    and refused their decorators (importing the calibration kernels raised "no locator available").
    ``import mmflow`` now gives it mmflow's cache folder, else a per-user temporary one. Here every
    ``__pycache__`` of a copy of the package is a file (cannot be a folder), $HOME and the cache
    variables point nowhere writable: the kernels compile, run and land in the temporary folder."""
    import os
    import shutil
    from pathlib import Path

    pkg = Path(offline.__file__).resolve().parent
    copy = tmp_path / "site" / "mmflow"
    shutil.copytree(pkg, copy, ignore=shutil.ignore_patterns("__pycache__"))
    for folder in [copy, *[p for p in copy.rglob("*") if p.is_dir()]]:
        (folder / "__pycache__").write_text("")  # numba's in-tree cache folder cannot be made
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "MMFLOW_CACHE_DIR", "XDG_CACHE_HOME")}
    env.update(HOME="/dev/null", PYTHONPATH=str(copy.parent), TMPDIR=str(tmp), PYTHONDONTWRITEBYTECODE="1")
    code = ("import os, numpy as np\n"
            "from mmflow.calibrate.baselines import to_matrix\n"
            "m = to_matrix(np.array([[1 + 2j]]), np.array([[0, 1]]), 2)\n"
            "print(m[0, 1, 0], os.environ['NUMBA_CACHE_DIR'])\n")
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    value, folder = out.stdout.split()
    assert complex(value) == 1 - 2j and Path(folder).parent == tmp
    assert any(Path(folder).rglob("*.nbi"))  # the compiled kernel was cached there


def test_numba_cache_folder_fallbacks_are_private(tmp_path, monkeypatch):
    """Without a home folder the numba cache falls back to a temporary folder only this user can write;
    a folder of that name that others can write is not used (numba unpickles what it finds there)."""
    import os

    from mmflow import compiled_cache

    monkeypatch.setattr(compiled_cache.tempfile, "gettempdir", lambda: str(tmp_path))
    monkeypatch.delitem(sys.modules, "numba", raising=False)  # as before numba's first import
    monkeypatch.setenv("NUMBA_CACHE_DIR", "")
    read_only = tmp_path / "pkg"
    read_only.mkdir()
    (read_only / "__pycache__").write_text("")  # the package's own cache folder cannot be made

    def no_home():
        raise RuntimeError("Could not determine home directory")

    monkeypatch.setattr(compiled_cache, "cache_dir", no_home)
    folder = compiled_cache.configure_numba_cache(read_only)
    assert folder is not None and folder.parent == tmp_path and os.environ["NUMBA_CACHE_DIR"] == str(folder)
    assert folder.stat().st_mode & 0o077 == 0
    monkeypatch.setenv("NUMBA_CACHE_DIR", "")
    folder.chmod(0o777)  # prepared by someone else, or open to them
    assert compiled_cache.configure_numba_cache(read_only) is None and not os.environ["NUMBA_CACHE_DIR"]
