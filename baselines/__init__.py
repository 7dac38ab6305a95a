"""DMRT baselines."""
