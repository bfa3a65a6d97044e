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

import numba
import numpy as np

from endo_io.pose import rigid_transform


@numba.njit(cache=True, nogil=True)
def _relative(poses: np.ndarray, a: int, b: int, i: int, j: int) -> float:
    """Entry (i, j) of R_aᵀ R_b for the rotations of poses a and b."""
    return (poses[a, 0, i] * poses[b, 0, j] + poses[a, 1, i] * poses[b, 1, j]
            + poses[a, 2, i] * poses[b, 2, j])


@numba.njit(cache=True, nogil=True)
def _local_line(stamps: np.ndarray, poses: np.ndarray, at: int, half_ns: int) -> np.ndarray:
    """The tricube-weighted line fit around pose ``at``, evaluated there: (6,) float64.

    Centre (3) and rotation vector relative to pose ``at`` (3); NaN when
    fewer than two poses within ±``half_ns`` have positive weight (one
    exactly ``half_ns`` away weighs 0) or fewer than three are in the window.
    """
    out = np.full(6, np.nan)
    n = stamps.shape[0]
    centre = stamps[at]
    lo = at
    while lo > 0 and stamps[lo - 1] >= centre - half_ns:
        lo -= 1
    hi = at + 1
    while hi < n and stamps[hi] <= centre + half_ns:
        hi += 1
    s0 = s1 = s2 = 0.0
    y0 = np.zeros(6)
    y1 = np.zeros(6)
    positive = 0
    for k in range(lo, hi):
        t = (stamps[k] - centre) / half_ns  # in [-1, 1]
        w = (1.0 - abs(t) ** 3) ** 3
        if w > 0.0:
            positive += 1
        # the rotations within a window differ by a few degrees: the
        # small-angle logarithm vee(R0ᵀR − (R0ᵀR)ᵀ)/2 is exact to O(θ³)
        value = np.empty(6)
        value[0] = poses[k, 0, 3]
        value[1] = poses[k, 1, 3]
        value[2] = poses[k, 2, 3]
        value[3] = 0.5 * (_relative(poses, at, k, 2, 1) - _relative(poses, at, k, 1, 2))
        value[4] = 0.5 * (_relative(poses, at, k, 0, 2) - _relative(poses, at, k, 2, 0))
        value[5] = 0.5 * (_relative(poses, at, k, 1, 0) - _relative(poses, at, k, 0, 1))
        s0 += w
        s1 += w * t
        s2 += w * t * t
        y0 += w * value
        y1 += (w * t) * value
    if hi - lo < 3 or positive < 2:
        return out
    # weighted least-squares line a + b·t at t = 0: the intercept
    # a = (S2·Y0 − S1·Y1) / (S0·S2 − S1²), positive for two distinct t of weight > 0
    out[:] = (s2 * y0 - s1 * y1) / (s0 * s2 - s1 * s1)
    return out


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
        self.capacity = int(capacity)
        # the held poses are rows [start, end) of arrays twice the capacity,
        # in stamp order: appending is a row write, and the last ``capacity``
        # rows move to the front once the arrays are full (amortised O(1))
        self._stamp_rows = np.zeros(2 * self.capacity, np.int64)
        self._pose_rows = np.zeros((2 * self.capacity, 4, 4))
        self._start = 0
        self._end = 0
        self._final: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return self._end - self._start

    @property
    def stamps(self) -> np.ndarray:
        """(n,) int64 stamps of the poses held, oldest first (a view: do not modify)."""
        return self._stamp_rows[self._start : self._end]

    @property
    def poses(self) -> np.ndarray:
        """(n, 4, 4) float64 raw poses held, oldest first (a view: do not modify)."""
        return self._pose_rows[self._start : self._end]

    def clear(self) -> None:
        """Forget every pose."""
        self._start = self._end = 0
        self._final.clear()

    def add(self, stamp_ns: int, T_world_camera: np.ndarray) -> None:
        """Record the (4, 4) pose of the frame at ``stamp_ns`` (increasing stamps)."""
        if self._end == len(self._stamp_rows):
            keep = self.capacity - 1
            self._stamp_rows[:keep] = self._stamp_rows[self._end - keep : self._end]
            self._pose_rows[:keep] = self._pose_rows[self._end - keep : self._end]
            self._start, self._end = 0, keep
        self._stamp_rows[self._end] = int(stamp_ns)
        self._pose_rows[self._end] = T_world_camera
        self._end += 1
        if self._end - self._start > self.capacity:
            self._start += 1
        oldest = int(self._stamp_rows[self._start])
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
        final = self._final.get(stamp_ns)
        if final is not None:
            return final
        stamps = self.stamps
        at = int(np.searchsorted(stamps, stamp_ns))
        if at >= len(stamps) or stamps[at] != stamp_ns:
            raise KeyError(f"no pose recorded at {stamp_ns} ns")
        poses = self.poses
        reference = poses[at]
        if self.half_window_ns == 0:
            return reference.copy()
        intercept = _local_line(stamps, poses, at, self.half_window_ns)
        if np.isnan(intercept[0]):
            result = reference.copy()
        else:
            result = rigid_transform(intercept[3:], intercept[:3])
            result[:3, :3] = reference[:3, :3] @ result[:3, :3]
        if stamps[-1] - stamp_ns >= self.half_window_ns:
            self._final[stamp_ns] = result
        return result
