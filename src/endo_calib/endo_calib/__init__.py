"""Gray-card photometric calibration (camera response, light map) and the correction node."""
