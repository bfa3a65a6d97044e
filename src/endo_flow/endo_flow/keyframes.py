"""A window of keyframes: the past views of each track, with their camera poses.

Triangulating a track needs views from camera centres far enough apart. At
the usual 5–15 mm/s a second of frames gives that; at slow motion it does not,
so frames are not all kept: a frame becomes a keyframe only once the camera
centre has moved ``min_step_m`` from the last keyframe (or turned
``min_turn_rad``), and the window keeps the last ``capacity`` keyframes, none
older than ``max_age_ns``. Slow motion thus spreads the same number of
keyframes over a longer time and still builds baseline; a still camera keeps
adding no keyframes (beyond what tracker noise moves it).

Each keyframe stores the camera-frame unit ray of every feature seen in it
(:meth:`endo_io.camera.CameraModel.pixels_to_rays`, computed once), so a
triangulation only rotates rays into the world.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from endo_io.pose import rotation_angle


@dataclass(frozen=True)
class Keyframe:
    """One kept view.

    Attributes:
        stamp_ns: image stamp, integer ns.
        T_world_camera: (4, 4) float64 camera pose, metres.
        ids: (N,) int64 track ids, sorted.
        rays: (N, 3) float64 unit rays of those tracks, camera frame.
        relative: (N,) float64 depth_relative at those tracks' pixels in
            this view (NaN where it has none), or None.
    """

    stamp_ns: int
    T_world_camera: np.ndarray
    ids: np.ndarray
    rays: np.ndarray
    relative: np.ndarray | None = None

    def sorted_by_id(self) -> Keyframe:
        """The same view with its tracks in id order."""
        order = np.argsort(self.ids, kind="stable")
        relative = None if self.relative is None else self.relative[order]
        return Keyframe(self.stamp_ns, self.T_world_camera, self.ids[order], self.rays[order],
                        relative)

    def with_pose(self, T_world_camera: np.ndarray) -> Keyframe:
        """The same view with another camera pose (e.g. a smoothed one)."""
        return Keyframe(self.stamp_ns, T_world_camera, self.ids, self.rays, self.relative)


@dataclass(frozen=True)
class TrackViews:
    """The views of a set of tracks, padded to a common count.

    Attributes:
        centres: (N, V, 3) float64 camera centres in world, metres.
        directions: (N, V, 3) float64 unit rays in world.
        valid: (N, V) bool, which of the V views saw the track.
        axes: (N, V, 3) float64 optical axes of the views in world, or None.
        relative: (N, V) float64 depth_relative of the track in each view
            (NaN where unknown), or None.
    """

    centres: np.ndarray
    directions: np.ndarray
    valid: np.ndarray
    axes: np.ndarray | None = None
    relative: np.ndarray | None = None


class KeyframeWindow:
    """The last keyframes (see the module docstring).

    Args:
        capacity: keyframes kept.
        min_step_m: camera-centre motion since the last keyframe that makes
            a new keyframe, metres.
        min_turn_rad: rotation since the last keyframe that also does.
        max_age_ns: keyframes older than this before the newest are dropped.
    """

    def __init__(
        self,
        capacity: int = 30,
        min_step_m: float = 0.8e-3,
        min_turn_rad: float = np.radians(2.0),
        max_age_ns: int = 4_000_000_000,
    ) -> None:
        if capacity < 2:
            raise ValueError(f"capacity must be >= 2, got {capacity}")
        if min_step_m < 0.0 or min_turn_rad < 0.0 or max_age_ns <= 0:
            raise ValueError("min_step_m, min_turn_rad must be >= 0 and max_age_ns > 0")
        self.capacity = capacity
        self.min_step_m = min_step_m
        self.min_turn_rad = min_turn_rad
        self.max_age_ns = max_age_ns
        self._frames: deque[Keyframe] = deque(maxlen=capacity)
        self._version = 0  # bumped on every change of the held keyframes
        self._table: _ViewTable | None = None

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def version(self) -> int:
        """A counter bumped on every change of the held keyframes (added, dropped, rescaled)."""
        return self._version

    @property
    def keyframes(self) -> tuple[Keyframe, ...]:
        """The keyframes held, oldest first."""
        return tuple(self._frames)

    def clear(self) -> None:
        """Forget every keyframe."""
        self._frames.clear()
        self._version += 1

    def wants(self, T_world_camera: np.ndarray) -> bool:
        """Whether a frame at this pose would become a keyframe."""
        if not self._frames:
            return True
        last = self._frames[-1].T_world_camera
        step = float(np.linalg.norm(T_world_camera[:3, 3] - last[:3, 3]))
        turn = float(rotation_angle(last[:3, :3].T @ T_world_camera[:3, :3]))
        return step >= self.min_step_m or turn >= self.min_turn_rad

    def add(self, keyframe: Keyframe) -> None:
        """Append a keyframe and drop those older than ``max_age_ns`` before it."""
        self._frames.append(keyframe.sorted_by_id())
        while self._frames and keyframe.stamp_ns - self._frames[0].stamp_ns > self.max_age_ns:
            self._frames.popleft()
        self._version += 1

    def scale_relative(self, factor: float) -> None:
        """Multiply every held keyframe's depth_relative by ``factor``.

        A gain or exposure step multiplies ρ by g, so depth_relative by
        1/√g from that frame on; the keyframes' samples are put on the new
        frames' footing so that a track's views still agree.
        """
        self._frames = deque(
            (frame if frame.relative is None else Keyframe(
                frame.stamp_ns, frame.T_world_camera, frame.ids, frame.rays,
                frame.relative * factor) for frame in self._frames),
            maxlen=self.capacity,
        )
        self._version += 1

    def _held_table(self, held: int) -> _ViewTable:
        """The first ``held`` keyframes' tracks as one table, built once per window change."""
        table = self._table
        if table is None or table.version != self._version or table.held != held:
            table = _ViewTable.build(list(self._frames)[:held], self._version)
            self._table = table
        return table

    def view_stamps(self, current: Keyframe | None = None) -> np.ndarray:
        """(V,) int64 stamps of the views :meth:`views` gathers, in its order."""
        stamps = [frame.stamp_ns for frame in self._frames]
        if current is not None:
            if stamps and stamps[-1] == current.stamp_ns:
                stamps.pop()
            stamps.append(current.stamp_ns)
        return np.array(stamps, np.int64)

    def views(
        self,
        ids: np.ndarray,
        current: Keyframe | None = None,
        pose_of: Callable[[Keyframe], np.ndarray] | None = None,
    ) -> TrackViews:
        """Gather every held view of the tracks ``ids``, plus ``current`` if given.

        Args:
            ids: (N,) int64 track ids.
            current: the present frame as a last view (its ids need not be
                sorted, and it need not be a keyframe), or None. Its own
                pose is used.
            pose_of: the (4, 4) pose to use for a held keyframe (e.g. a
                smoothed one); None uses each keyframe's recorded pose.

        Returns:
            The views, V = keyframes held (+ 1 with ``current``), oldest
            first. A keyframe that is also ``current`` is not counted twice
            (``current`` replaces it).
        """
        ids = np.asarray(ids, np.int64)
        held = len(self._frames)
        if current is not None and held and self._frames[-1].stamp_ns == current.stamp_ns:
            held -= 1
        frames = [self._frames[k] for k in range(held)]
        n, v = len(ids), held + (current is not None)
        poses = np.empty((v, 4, 4))
        for k, frame in enumerate(frames):
            poses[k] = frame.T_world_camera if pose_of is None else pose_of(frame)
        if current is not None:
            poses[held] = current.T_world_camera
        centres = np.empty((n, v, 3))
        centres[:] = poses[:, :3, 3]
        axes = np.empty((n, v, 3))
        axes[:] = poses[:, :3, 2]
        directions = np.zeros((n, v, 3))
        relative = np.full((n, v), np.nan)
        valid = np.zeros((n, v), bool)
        if held and n:
            # one sorted search for every (keyframe, track) pair
            table = self._held_table(held)
            found, rows = table.lookup(ids)
            valid[:, :held] = found
            cam = table.rays[rows]  # (n, held, 3) camera-frame rays, garbage where not found
            cam[~found] = 0.0
            # world ray = R @ ray, as a batched matmul over the keyframes: (held, n, 3)
            world = np.matmul(cam.transpose(1, 0, 2), poses[:held, :3, :3].transpose(0, 2, 1))
            directions[:, :held] = world.transpose(1, 0, 2)
            relative[:, :held] = np.where(found, table.relative[rows], np.nan)
        if current is not None and n:
            if np.array_equal(current.ids, ids):
                seen = np.ones(n, bool)
                at = np.arange(n)
            else:
                order = np.argsort(current.ids, kind="stable")
                sorted_ids = current.ids[order]
                at = np.minimum(np.searchsorted(sorted_ids, ids), max(len(sorted_ids) - 1, 0))
                seen = sorted_ids[at] == ids if len(sorted_ids) else np.zeros(n, bool)
                at = order[at] if len(sorted_ids) else at
            R = current.T_world_camera[:3, :3]
            directions[seen, held] = current.rays[at[seen]] @ R.T
            if current.relative is not None:
                relative[seen, held] = current.relative[at[seen]]
            valid[:, held] = seen
        return TrackViews(centres, directions, valid, axes, relative)


@dataclass(frozen=True)
class _ViewTable:
    """The tracks of several keyframes, concatenated and searchable by (keyframe, id).

    Attributes:
        version: the window's version it was built from.
        held: keyframes in it.
        keys: (M,) int64 sorted keys ``k · span + id`` (k: keyframe slot).
        span: larger than every id in it.
        rays: (M, 3) float64 camera-frame rays, by key.
        relative: (M,) float64 depth_relative by key (NaN from a keyframe
            without).
    """

    version: int
    held: int
    keys: np.ndarray
    span: int
    rays: np.ndarray
    relative: np.ndarray

    @classmethod
    def build(cls, frames: list[Keyframe], version: int) -> _ViewTable:
        sizes = [len(frame.ids) for frame in frames]
        span = 1 + max((int(frame.ids[-1]) for frame in frames if len(frame.ids)), default=0)
        slot = np.repeat(np.arange(len(frames), dtype=np.int64), sizes)
        ids = np.concatenate([frame.ids for frame in frames]) if frames else np.empty(0, np.int64)
        rays = np.concatenate([frame.rays for frame in frames]) if frames else np.empty((0, 3))
        relative = np.concatenate(
            [np.full(len(frame.ids), np.nan) if frame.relative is None else frame.relative
             for frame in frames]) if frames else np.empty(0)
        return cls(version, len(frames), slot * span + ids, span, rays, relative)

    def lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each of ``ids`` sits in each keyframe: ((N, held) bool found, (N, held) rows)."""
        if len(self.keys) == 0:
            return np.zeros((len(ids), self.held), bool), np.zeros((len(ids), self.held), np.int64)
        inside = (ids >= 0) & (ids < self.span)
        query = np.arange(self.held, dtype=np.int64) * self.span + np.where(inside, ids, 0)[:, None]
        rows = np.minimum(np.searchsorted(self.keys, query), len(self.keys) - 1)
        found = (self.keys[rows] == query) & inside[:, None]
        return found, rows
