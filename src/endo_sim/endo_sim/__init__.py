"""Endoscope simulator with physically based photometry, tracker simulation and ground truth."""
