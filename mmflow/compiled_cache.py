"""Where numba keeps mmflow's compiled kernels (the one place where this is set).

mmflow's numba kernels are compiled with ``cache=True``: compiled once per machine, loaded by every
later process (each dask worker, each command) in milliseconds. numba looks for a folder it can
write in this order: ``$NUMBA_CACHE_DIR``, the ``__pycache__`` beside the module, then a user-wide
folder under ``$HOME``. When none is writable -- a read-only installation (a shared HPC software
tree, a container image run as another user) with no writable home -- it refuses the decorator
itself, and importing the calibration kernels failed with ``RuntimeError: cannot cache function
...: no locator available``. :func:`configure_numba_cache` runs before numba is imported
(``import mmflow``): if ``$NUMBA_CACHE_DIR`` is unset and the package's ``__pycache__`` cannot be
written, it points numba at mmflow's cache folder (:func:`mmflow.offline.cache_dir`), else at a
per-user folder in the temporary directory. It holds only what numba can rebuild.
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


def configure_numba_cache(package_dir=Path(__file__).resolve().parent):
    """Set ``$NUMBA_CACHE_DIR`` where numba would find no writable cache folder; return the folder set
    (None: numba's own choice stands, or numba was imported already and reads no more settings)."""
    if os.environ.get("NUMBA_CACHE_DIR") or "numba" in sys.modules:
        return None
    if _writable(package_dir / "__pycache__"):
        return None
    uid = os.getuid() if hasattr(os, "getuid") else os.getpid()
    for folder in (cache_dir() / "numba", Path(tempfile.gettempdir()) / f"mmflow-numba-{uid}"):
        if _writable(folder):
            os.environ["NUMBA_CACHE_DIR"] = str(folder)
            return folder
    return None
