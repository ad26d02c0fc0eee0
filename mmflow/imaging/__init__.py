"""Imaging per m block: Tikhonov and alternatives, L-curves, m-filters, HEALPix maps."""
