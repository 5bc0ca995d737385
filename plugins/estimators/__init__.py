"""Estimator plugins: depth from a tactile image, force from depth."""
