"""Keep astropy (and pyuvdata through it) from touching the network (the one place where this is set).

The machines mmflow runs on (and HPC compute nodes in general) often have no internet.
astropy would otherwise try to download IERS-A tables for UT1-UTC and polar motion;
we use the bundled ``astropy-iers-data`` tables and degrade gracefully beyond them.

astropy also downloads its observatory list (``coordinates/sites.json``) the first time anyone
asks for site names, and pyuvdata asks whenever it reads a MeasurementSet that does not store
its telescope location (``pyuvdata.telescopes.known_telescopes``): a telescope name astropy does
not know (``LWASV``, ``OVRO_MMA``) then failed with a URL error. :func:`offline_site_registry`
gives astropy a registry with no named site when the list is not in astropy's cache, so pyuvdata
takes such a telescope's location from the file itself (its antenna positions).

astropy parses the bundled IERS tables (text, ~1.5-2 s) in every process on its first UT1 or
polar-motion lookup, i.e. in every dask worker and every ``mmflow`` command that rotates a frame.
:func:`configure_astropy` makes that parse happen once per machine: the parsed table is kept in
mmflow's cache folder (:func:`cache_dir`) and loaded from there (~15 ms, the same values).
"""
import os
import pickle
import tempfile
import warnings
from pathlib import Path

from astropy.utils import iers
from astropy.utils.data import conf as data_conf
from astropy.utils.data import is_url_in_cache


def configure_astropy():
    """Set astropy's IERS and data-download options to offline mode (idempotent)."""
    iers.conf.auto_download = False
    iers.conf.auto_max_age = None
    iers.conf.iers_degraded_accuracy = "warn"
    data_conf.allow_internet = False
    warnings.filterwarnings("ignore", module="astropy.utils.iers")
    if not getattr(iers.IERS_Auto.read, "_mmflow_cached", False):
        iers.IERS_Auto.read = classmethod(_cached_read(iers.IERS_Auto.read.__func__))


def cache_dir():
    """mmflow's cache folder: ``$MMFLOW_CACHE_DIR``, else ``$XDG_CACHE_HOME/mmflow`` (``~/.cache/mmflow``).

    It holds only files mmflow can rebuild (the parsed IERS table); deleting it is always safe.
    """
    if os.environ.get("MMFLOW_CACHE_DIR"):
        return Path(os.environ["MMFLOW_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "mmflow"


def _iers_cache_path():
    """The cache file of the bundled tables now installed: named by the astropy and astropy-iers-data
    versions and the two files' sizes and modification times (a changed table is parsed again)."""
    import astropy  # deferred: only for the version (`import mmflow` imports this module)
    import astropy_iers_data  # deferred: only for the version

    stamp = [astropy.__version__, astropy_iers_data.__version__]
    for f in (iers.IERS_A_FILE, iers.IERS_B_FILE):
        st = os.stat(f)
        stamp += [str(st.st_size), str(st.st_mtime_ns)]
    return cache_dir() / f"iers-auto-{'-'.join(stamp)}.pickle"


def _cached_read(read):
    """``IERS_Auto.read`` that keeps the parsed bundled table in :func:`cache_dir` (other files: astropy's read)."""

    def cached(cls, file=None, readme=None):
        if cls is not iers.IERS_Auto or file is not None or readme is not None or os.path.exists("finals2000A.all"):
            return read(cls, file, readme)  # astropy's own choice of file (a local finals2000A.all first)
        try:
            path = _iers_cache_path()
        except (OSError, RuntimeError, KeyError):  # no home folder (some containers): no cache
            return read(cls)
        try:
            table = pickle.loads(path.read_bytes())
            if isinstance(table, iers.IERS_Auto):
                return table
        except Exception:  # missing, truncated or from another Python: parse again and replace it
            pass
        table = read(cls)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=path.parent, delete=False, suffix=".tmp") as fh:
                fh.write(pickle.dumps(table, protocol=pickle.HIGHEST_PROTOCOL))
            os.replace(fh.name, path)  # atomic: concurrent processes read a whole file or none
        except OSError:  # a read-only home: every process parses, as astropy alone would
            pass
        return table

    cached._mmflow_cached = True
    cached.astropy_read = read  # astropy's own parse (tests compare the two)
    return cached


def offline_site_registry():
    """Make astropy's site registry available without a download (idempotent; call before pyuvdata reads).

    astropy's ``sites.json`` is read from astropy's cache when it is there (no download is tried);
    otherwise the registry holds one site with an empty name (``EarthLocation.get_site_names`` is
    then non-empty, so astropy never tries again, and pyuvdata drops empty names, so no telescope
    is matched by it). Returns the number of named sites known.
    """
    # deferred: astropy.coordinates takes 0.1-0.2 s to import (docs/performance.md); `import mmflow` loads this module
    from astropy.coordinates import EarthLocation
    from astropy.coordinates.sites import SiteRegistry

    configure_astropy()
    if not EarthLocation._site_registry:
        urls = [base + "coordinates/sites.json" for base in (data_conf.dataurl, data_conf.dataurl_mirror)]
        with warnings.catch_warnings():  # no cache folder yet: astropy warns while answering "not cached"
            warnings.simplefilter("ignore")
            cached = any(is_url_in_cache(u) for u in urls)
        if cached:
            EarthLocation._get_site_registry()  # read from astropy's cache
        else:
            reg = SiteRegistry()
            reg.add_site([""], EarthLocation.from_geocentric(0.0, 0.0, 0.0, unit="m"))
            EarthLocation._site_registry = reg
    return len([n for n in EarthLocation._site_registry.names if n])
