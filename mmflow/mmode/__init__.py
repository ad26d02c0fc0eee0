"""m-mode analysis: sidereal regridding, the m-mode transform, transfer matrices, normal equations."""
