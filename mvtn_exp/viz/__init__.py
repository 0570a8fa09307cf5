"""Figures: view grids, camera plots, view histograms and curves."""
