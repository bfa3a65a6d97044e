"""Shape from shading (Oren-Nayar, orthographic Eikonal and near-light perspective models) by fast sweeping."""
