"""Scenes to benchmark on: the synthetic laser-scan generator and real-data loaders."""
