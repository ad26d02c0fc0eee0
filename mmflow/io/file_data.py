"""What a reader returns for one input file (every reader's common type, imported one way)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class FileData:
    """One file's rows: times, antennas, LSTs and the kept polarisations of the kept channels."""

    time_jd: np.ndarray  # (nblt,)
    ant1: np.ndarray  # (nblt,) antenna numbers
    ant2: np.ndarray
    lst: np.ndarray  # (nblt,) rad
    vis: np.ndarray  # (nblt, nfreq, npol) complex, the kept polarisations, Jy
    flags: np.ndarray  # (nblt, nfreq, npol) bool
    nsample: np.ndarray  # (nblt, nfreq, npol) float
    freqs: np.ndarray  # (nfreq,) Hz
