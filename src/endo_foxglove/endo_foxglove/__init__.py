"""Live viewing of the endo3d graph in Foxglove: the endo-foxglove WebSocket bridge."""
