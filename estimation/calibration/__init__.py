"""Camera calibration: from photos of a known target (`checkerboard`), or a focal length from the verified
pairs' geometry alone (`self_calibration`)."""
