"""Independent time-domain simulation of drift scans (no transfer matrices inside)."""
