"""Embree ground truth: ray casts of a reference mesh, error metrics and heat maps."""
