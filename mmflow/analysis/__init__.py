"""Science products and measurements on maps: peaks, FWHM, noise, flux scale."""
