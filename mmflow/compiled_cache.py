"""Where numba keeps mmflow's compiled kernels (the one place where this is set).

mmflow's numba kernels are compiled with ``cache=True``: compiled once per machine, loaded by every
later process (each dask worker, each command) in milliseconds. numba looks for a folder it can
write in this order: ``$NUMBA_CACHE_DIR``, the ``__pycache__`` beside the module, then a user-wide
folder under ``$HOME``. When none is writable -- a read-only installation (a shared HPC software
tree, a container image run as another user) with no writable home -- it refuses the decorator
itself, and importing the calibration kernels failed with ``RuntimeError: cannot cache function
...: no locator available``. :func:`configure_numba_cache` runs before numba is imported
(``import mmflow``): if ``$NUMBA_CACHE_DIR`` is unset and the package's ``__pycache__`` cannot be
written, it points numba (in this process and the workers it starts) at mmflow's cache folder
(:func:`mmflow.offline.cache_dir`), else at a folder of the temporary directory that only this
user can write (numba unpickles what it finds there). It holds only what numba can rebuild.
"""
import os
import sys
import tempfile
from pathlib import Path

from mmflow.offline import cache_dir


def _writable(folder):
    """Whether a file can be created in ``folder`` (made if missing), as numba itself checks."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
        return True
    except OSError:
        return False


def _private_temp_folder():
    """``<tmp>/mmflow-numba-<uid>``, made mode 0700; None if it exists and another user owns it or
    others can write it (a folder another user prepared could feed numba a cache of their making)."""
    uid = os.getuid() if hasattr(os, "getuid") else None
    folder = Path(tempfile.gettempdir()) / f"mmflow-numba-{uid if uid is not None else 'user'}"
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        st = folder.stat()
    except OSError:
        return None
    if uid is not None and (st.st_uid != uid or st.st_mode & 0o022):
        return None
    return folder


def configure_numba_cache(package_dir=Path(__file__).resolve().parent):
    """Set ``$NUMBA_CACHE_DIR`` when the package's ``__pycache__`` cannot be written; return the folder
    set (None: numba's own choice stands, also when numba was imported before mmflow)."""
    if os.environ.get("NUMBA_CACHE_DIR") or "numba" in sys.modules:
        return None
    if _writable(package_dir / "__pycache__"):
        return None
    try:
        candidates = [cache_dir() / "numba"]
    except (RuntimeError, KeyError, OSError):  # no home folder at all
        candidates = []
    for folder in candidates + [_private_temp_folder()]:
        if folder is not None and _writable(folder):
            os.environ["NUMBA_CACHE_DIR"] = str(folder)
            return folder
    return None
