"""Camera calibration from photos of a known target."""
