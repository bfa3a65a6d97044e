"""Message/numpy conversions, camera model, QoS presets and rosbag2-compatible MCAP replay and record for endo3d."""
