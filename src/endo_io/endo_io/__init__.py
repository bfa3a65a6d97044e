"""endo3d message I/O: message/numpy conversions, camera model, QoS presets,
rosbag2-compatible MCAP reading and writing, replay and record."""
