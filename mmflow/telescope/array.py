"""The telescope: site, antennas, baselines (with autocorrelations), frequencies, beam."""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Optional

import numpy as np
from astropy import units as u

from mmflow.conventions import SPEED_OF_LIGHT, enu_to_equatorial_matrix
from mmflow.errors import InputError
from mmflow.telescope.beams import Beam
from mmflow.telescope.layout import Layout



@dataclass
class Telescope:
    """A drift-scanning array.

    Attributes
    ----------
    layout : Layout
    beam : Beam
    freqs_hz : ndarray
    integration_s : float
    include_autos : bool
    """

    layout: Layout
    beam: Beam
    freqs_hz: np.ndarray
    integration_s: float = 13.0
    include_autos: bool = True
    channel_width_hz: float = 24e3
    pairs: Optional[np.ndarray] = None

    def __post_init__(self):
        self.freqs_hz = np.atleast_1d(np.asarray(self.freqs_hz, float))
        if np.any(self.freqs_hz <= 0):
            raise InputError("telescope", "freqs_hz", "non-positive frequency", "give frequencies in Hz")
        for f in self.freqs_hz:
            self.beam.check_frequency(f)

    @property
    def lat_rad(self):
        return np.deg2rad(self.layout.lat_deg)

    @property
    def n_ant(self):
        return self.layout.n_ant

    @property
    def location(self):
        """The array centre as an astropy ``EarthLocation``."""
        # deferred: astropy.coordinates takes 0.1-0.2 s to import (docs/performance.md)
        from astropy.coordinates import EarthLocation

        return EarthLocation.from_geodetic(self.layout.lon_deg * u.deg, self.layout.lat_deg * u.deg,
                                           self.layout.height_m * u.m)

    def antenna_pairs(self):
        """Antenna index pairs ``(i, j)``: as given (ingested data), else ``i <= j`` i-major."""
        if self.pairs is not None:
            return np.asarray(self.pairs)
        i, j = np.triu_indices(self.n_ant, k=0 if self.include_autos else 1)
        return np.stack([i, j], axis=1)

    def baselines_enu(self, pairs=None):
        """Baseline vectors ``x_j - x_i`` in metres, ENU, shape (n_bl, 3)."""
        pairs = self.antenna_pairs() if pairs is None else np.asarray(pairs)
        return self.layout.enu[pairs[:, 1]] - self.layout.enu[pairs[:, 0]]

    def antennas_equatorial(self):
        """Antenna positions in the sky frame at ``phi = 0`` (metres, x to RA=0, z to pole)."""
        return self.layout.enu @ enu_to_equatorial_matrix(self.lat_rad).T

    def baseline_lmax(self, freq_hz, lmax, pairs=None):
        """Per-baseline lmax: ``min(lmax, ceil(1.1 * 2 pi |b| / lambda) + beam.lmax_hint)``.

        The beam term is the floor: even an autocorrelation has structure on the beam's
        scale. Coefficients beyond ``lmax_b`` are below ~1e-6 of the baseline's peak for
        smooth beams (tested in ``tests/unit/mmode/test_transfer.py``).
        """
        b = np.linalg.norm(self.baselines_enu(pairs), axis=1)
        est = np.ceil(1.1 * 2 * np.pi * b * freq_hz / SPEED_OF_LIGHT).astype(int) + int(self.beam.lmax_hint)
        return np.minimum(est, lmax)

    def check_lmax(self, lmax, freq_hz=None):
        """Warn when ``lmax`` is smaller than the longest baseline needs; return the estimate."""
        freq_hz = self.freqs_hz.max() if freq_hz is None else freq_hz
        need = int(self.baseline_lmax(freq_hz, 10**9).max())
        if lmax < need:
            warnings.warn(f"lmax={lmax} is below the {need} the longest baseline needs at "
                          f"{freq_hz / 1e6:.2f} MHz: the map resolution is limited by lmax and "
                          f"power beyond it aliases into the model (raise lmax to ~{need})",
                          stacklevel=2)
        return need

    def describe(self):
        return {"n_ant": self.n_ant, "lat_deg": self.layout.lat_deg, "lon_deg": self.layout.lon_deg,
                "height_m": self.layout.height_m, "freqs_hz": self.freqs_hz.tolist(),
                "integration_s": self.integration_s, "include_autos": self.include_autos,
                "beam": self.beam.describe(), "layout_provenance": self.layout.provenance}
