"""Optical tracker (ROS, OpenIGTLink, NDI, CSV) to camera pose.

Includes the hand-eye and clock calibration (``endo-handeye``).
"""
