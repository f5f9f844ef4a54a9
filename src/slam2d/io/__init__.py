"""Readers and writers for external formats (datasets, graphs, trajectories)."""
