"""The `priors` stage: Gaussian mixtures on log distance ratios of true wheel-vehicle and wheel-wheel pairs."""
