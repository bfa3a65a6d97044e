"""Smoothing the camera poses of past frames by local linear regression over time.

An optical tracker's poses carry white noise: 0.25 mm and 0.1° RMS at the
marker, and through the 30 cm lever arm to the camera about 0.5 mm of camera
centre per sample, more than the camera moves between two frames. The scope
moves smoothly, so for a frame that lies a little in the past the poses of
the frames around it, before and after, pin its pose down far better than
its own sample does. :class:`PoseSmoother` keeps the recent frame poses and
returns, for a past stamp, the local linear fit (tricube weights over
±``half_window_ns``) of the camera centre and of the rotation (as rotation
vectors relative to the pose at that stamp), evaluated at the stamp. With
poses on both sides of the stamp this is unbiased for motion of constant
velocity; at 30 fps with ±0.3 s the noise falls about 3.5×.

Keyframes are triangulated with smoothed poses; the current frame keeps its
own pose (it has no future yet), so its error stays white from frame to
frame and averages out in the scale filter instead of biasing whole windows.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from endo_io.pose import rigid_transform


class PoseSmoother:
    """Recent stamped camera poses and their smoothed values (see the module docstring).

    Args:
        half_window_ns: half-width of the regression window, integer ns
            (0 turns smoothing off: :meth:`smoothed` returns the raw pose).
        capacity: poses kept (the oldest go first).
    """

    def __init__(self, half_window_ns: int = 300_000_000, capacity: int = 600) -> None:
        if half_window_ns < 0 or capacity < 2:
            raise ValueError("half_window_ns must be >= 0 and capacity >= 2")
        self.half_window_ns = int(half_window_ns)
        self._stamps: deque[int] = deque(maxlen=capacity)
        self._poses: deque[np.ndarray] = deque(maxlen=capacity)
        self._final: dict[int, np.ndarray] = {}
        self._stamp_array: np.ndarray | None = None
        self._pose_array: np.ndarray | None = None

    def clear(self) -> None:
        """Forget every pose."""
        self._stamps.clear()
        self._poses.clear()
        self._final.clear()
        self._stamp_array = None
        self._pose_array = None

    def add(self, stamp_ns: int, T_world_camera: np.ndarray) -> None:
        """Record the (4, 4) pose of the frame at ``stamp_ns`` (increasing stamps)."""
        self._stamps.append(int(stamp_ns))
        self._poses.append(np.asarray(T_world_camera, np.float64))
        self._stamp_array = None
        self._pose_array = None
        oldest = self._stamps[0]
        for stamp in [s for s in self._final if s < oldest]:
            del self._final[stamp]

    def smoothed(self, stamp_ns: int) -> np.ndarray:
        """The smoothed (4, 4) pose at ``stamp_ns``, which must be one recorded.

        A stamp whose window is complete (the newest pose is at least
        ``half_window_ns`` later) gets a result that no later pose changes;
        it is computed once and cached.

        Raises:
            KeyError: ``stamp_ns`` was not recorded (or has been dropped).
        """
        if stamp_ns in self._final:
            return self._final[stamp_ns]
        if self._stamp_array is None:
            self._stamp_array = np.fromiter(self._stamps, np.int64, len(self._stamps))
        stamps = self._stamp_array
        at = int(np.searchsorted(stamps, stamp_ns))
        if at >= len(stamps) or stamps[at] != stamp_ns:
            raise KeyError(f"no pose recorded at {stamp_ns} ns")
        reference = self._poses[at]
        if self.half_window_ns == 0:
            return reference
        lo = int(np.searchsorted(stamps, stamp_ns - self.half_window_ns))
        hi = int(np.searchsorted(stamps, stamp_ns + self.half_window_ns, side="right"))
        t = (stamps[lo:hi] - stamp_ns) / self.half_window_ns  # in [-1, 1]
        weight = (1.0 - np.abs(t) ** 3) ** 3
        # a line needs two poses of positive weight (one exactly half_window_ns away weighs 0)
        if hi - lo < 3 or np.count_nonzero(weight > 0.0) < 2:
            result = reference
        else:
            if self._pose_array is None:  # once per added pose, not per keyframe
                self._pose_array = np.stack(self._poses)
            poses = self._pose_array[lo:hi]
            relative = reference[:3, :3].T @ poses[:, :3, :3]
            # the rotations within a window differ by a few degrees: the
            # small-angle logarithm vee(R − Rᵀ)/2 is exact to O(θ³)
            rotvec = 0.5 * np.stack([relative[:, 2, 1] - relative[:, 1, 2],
                                      relative[:, 0, 2] - relative[:, 2, 0],
                                      relative[:, 1, 0] - relative[:, 0, 1]], axis=1)
            values = np.concatenate([poses[:, :3, 3], rotvec], axis=1)  # (n, 6)
            # weighted linear fit, evaluated at t = 0: the intercept
            design = np.stack([np.ones_like(t), t], axis=1)
            normal = design.T @ (design * weight[:, None])
            coef = np.linalg.solve(normal, design.T @ (values * weight[:, None]))
            centre, rotation = coef[0, :3], coef[0, 3:]
            result = rigid_transform(rotation, centre)
            result[:3, :3] = reference[:3, :3] @ result[:3, :3]
        if stamps[-1] - stamp_ns >= self.half_window_ns:
            self._final[stamp_ns] = result
        return result
