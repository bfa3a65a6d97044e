"""Optical tracker (ROS, OpenIGTLink, NDI, CSV) to camera pose through hand-eye and clock calibration."""
