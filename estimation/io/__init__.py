"""Inputs (image folders, calibration, match files) and outputs (COLMAP, PLY, JSON, figures)."""
