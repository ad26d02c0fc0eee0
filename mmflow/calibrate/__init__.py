"""Per-integration calibration kernels: gains (Stefcal), autocorrelation ripple, peeling with
direction-dependent gains, terrestrial interference templates and source-model fits.

Kernels take in-memory arrays (visibilities ``(time, baseline, pol)``, weights, antenna
``pairs``, model coherencies) and return solution arrays; solving and applying are separate
functions so corrections can be applied on read. See ``docs/calibration.md``.
"""
