"""Lucas-Kanade flow and tracker poses to absolute scale, metric depth and
world-frame point clouds (not built yet)."""
