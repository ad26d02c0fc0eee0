"""Input/output: ingest with pyuvdata, zarr stores, FITS/PNG export."""
