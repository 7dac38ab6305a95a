"""Benchmarks: synthetic and real scenes, experiments, the report builder."""
