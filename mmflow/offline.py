"""Keep astropy from touching the network (the one place where this is set).

The machines mmflow runs on (and HPC compute nodes in general) often have no internet.
astropy would otherwise try to download IERS-A tables for UT1-UTC and polar motion;
we use the bundled ``astropy-iers-data`` tables and degrade gracefully beyond them.
"""
import warnings

from astropy.utils import iers
from astropy.utils.data import conf as data_conf


def configure_astropy():
    """Set astropy's IERS and data-download options to offline mode (idempotent)."""
    iers.conf.auto_download = False
    iers.conf.auto_max_age = None
    iers.conf.iers_degraded_accuracy = "warn"
    data_conf.allow_internet = False
    warnings.filterwarnings("ignore", module="astropy.utils.iers")
