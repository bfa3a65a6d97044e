"""Gray-card photometric calibration (camera response and light map) and the image correction node."""
