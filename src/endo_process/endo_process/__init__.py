"""endo-process: a recording in, the live graph's outputs out, offline and deterministic.

:func:`endo_process.runner.process_bag` runs, frame by frame and without
DDS, the same cores the live nodes call: the photometric correction
(``endo_calib``), shape from shading warm-started (``endo_sfs``), the tracker
bridge's chain (``endo_tracker_bridge.chain``) and the flow stage
(``endo_flow``), and writes a rosbag2 MCAP with the live graph's topics.
``endo-process`` (:mod:`endo_process.cli`) is its command line.
"""
