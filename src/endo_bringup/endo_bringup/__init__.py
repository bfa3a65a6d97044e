"""Launch and demo entry points that wire the endo3d nodes into one graph."""
