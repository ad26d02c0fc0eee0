"""Brightness units, converted in this one place.

Rayleigh-Jeans: ``I_nu [Jy/sr] = 2 k T nu^2 / c^2 / 1e-26``.
"""
import numpy as np
from mmflow.conventions import SPEED_OF_LIGHT

K_BOLTZMANN = 1.380649e-23
JY = 1e-26


def jy_per_sr_per_kelvin(freq_hz):
    """Jy/sr of 1 K of Rayleigh-Jeans brightness temperature at ``freq_hz``."""
    return 2 * K_BOLTZMANN * np.asarray(freq_hz, float) ** 2 / SPEED_OF_LIGHT**2 / JY


def kelvin_to_jy_per_sr(temp_k, freq_hz):
    """Brightness temperature (K) to specific intensity (Jy/sr)."""
    return np.asarray(temp_k) * jy_per_sr_per_kelvin(freq_hz)


def jy_per_sr_to_kelvin(intensity, freq_hz):
    """Specific intensity (Jy/sr) to brightness temperature (K)."""
    return np.asarray(intensity) / jy_per_sr_per_kelvin(freq_hz)


def convert(values, from_unit, to_unit, freq_hz):
    """Convert between ``"K"`` and ``"Jy/sr"``."""
    if from_unit == to_unit:
        return np.asarray(values)
    if (from_unit, to_unit) == ("K", "Jy/sr"):
        return kelvin_to_jy_per_sr(values, freq_hz)
    if (from_unit, to_unit) == ("Jy/sr", "K"):
        return jy_per_sr_to_kelvin(values, freq_hz)
    raise ValueError(f"unknown unit conversion {from_unit} -> {to_unit} (use 'K' or 'Jy/sr')")
