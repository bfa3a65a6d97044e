"""Shared settings for the cross-package integration tests."""
