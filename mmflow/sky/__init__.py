"""Sky models: point and Gaussian sources with published spectra, diffuse maps, alm helpers."""
