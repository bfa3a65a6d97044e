"""PoseSmoother when the neighbours sit exactly at the window's edges (weight 0).

Found by the soak (issue 16): with frames 300 ms apart (newest-frame skipping at
~3 fps) the window held the pose and two neighbours at exactly ±half_window_ns,
whose weights are 0, and the weighted fit raised ``LinAlgError: Singular
matrix`` ("unexpected" drops on flow's /diagnostics).
"""

from __future__ import annotations

import numpy as np

from endo_flow.pose_smoothing import PoseSmoother
from endo_io.pose import rigid_transform

HALF_NS = 300_000_000


def test_neighbours_at_the_window_edges_give_the_recorded_pose():
    smoother = PoseSmoother(HALF_NS)
    poses = [rigid_transform(np.array([0.0, 0.0, 0.01 * k]), np.array([0.001 * k, 0.0, 0.0]))
             for k in range(3)]
    for k, pose in enumerate(poses):
        smoother.add(k * HALF_NS, pose)
    np.testing.assert_array_equal(smoother.smoothed(HALF_NS), poses[1])


def test_one_weighted_neighbour_inside_the_window_is_still_a_fit():
    smoother = PoseSmoother(HALF_NS)
    stamps = [0, HALF_NS, HALF_NS + HALF_NS // 2, 2 * HALF_NS]
    for stamp in stamps:  # x moves 1 mm per half window
        smoother.add(stamp, rigid_transform(np.zeros(3), np.array([0.001 * stamp / HALF_NS,
                                                                   0.0, 0.0])))
    # poses on a line in time: the local linear fit returns the line's value
    out = smoother.smoothed(HALF_NS)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out[:3, 3], [0.001, 0.0, 0.0], atol=1e-12)
