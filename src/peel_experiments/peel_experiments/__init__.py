"""Experiments (4.4), grids and the sweep (4.5), reports, the soak and the benchmarks."""
