"""Rerun recordings with their blueprints: the mechanism sweep, a FEM run, gait and contact."""
