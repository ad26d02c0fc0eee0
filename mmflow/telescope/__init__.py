"""Telescope description: antenna layouts, baselines, per-baseline lmax and beams."""
from mmflow.telescope.layout import Layout, load_layout, ovro_lwa_layout
from mmflow.telescope.array import Telescope

__all__ = ["Layout", "load_layout", "ovro_lwa_layout", "Telescope"]
