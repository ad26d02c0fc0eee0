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
"""
import warnings

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
