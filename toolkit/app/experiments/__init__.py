"""Experiment runners: standard cases on the phantom and the comparison of the FEM methods."""
