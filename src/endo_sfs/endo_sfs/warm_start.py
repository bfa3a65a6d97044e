"""What an SFS process keeps between frames, and which frames a worker solves.

:class:`WarmStartChain` holds the newest solved frames (the process's own
and, with several workers, the others' depth images), and hands out the warm
start of a new frame: the solved frame nearest before it, moved by the
camera motion between the two when both poses are known
(:func:`endo_sfs.pose_prediction.predict_warm_start`), as it stands
otherwise. The translation needs the depth scale (metres per unit of
depth_relative): the caller's (``endo_flow``'s scale topic) when given, else
one fitted on the chain's own consecutive solutions
(:func:`endo_sfs.pose_prediction.estimate_metres_per_unit`); without either,
the rotation alone.

:func:`frame_owner` and :class:`FrameDealer` split a stream among
``worker_count`` processes by stamp alone, so that workers agree without
talking to each other.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from endo_io.camera import CameraModel
from endo_sfs.errors import SfsInputError
from endo_sfs.grid import solve_grid
from endo_sfs.options import SfsOptions
from endo_sfs.orthographic import SolveInfo
from endo_sfs.pose_prediction import (
    PredictedStart,
    estimate_metres_per_unit,
    predict_warm_start,
    relative_motion,
)
from endo_sfs.relative_depth import SfsSolution, log_distance_nodes

#: A pose lookup: the (4, 4) T_world_camera at a stamp (ns), or None if unknown.
PoseLookup = Callable[[int], np.ndarray | None]

#: Weight of a new scale fit in the chain's running estimate (in ln s).
SCALE_UPDATE_WEIGHT = 0.2
#: Solved frames a chain keeps.
DEFAULT_KEEP = 4


def frame_owner(stamp_ns: int, worker_count: int, frame_period_ns: int, phase_ns: int = 0) -> int:
    """The worker (0 … worker_count − 1) that solves the frame stamped ``stamp_ns``.

    Frames are dealt round-robin by their slot: the stamp minus the
    stream's phase (``phase_ns``, where in the period its frames fall),
    rounded to a multiple of ``frame_period_ns``. Every worker computes the
    same owner from the stamp alone, so each frame is solved by exactly one
    worker, and consecutive frames go to consecutive workers; jitter up to
    half a period around the phase changes nothing.
    """
    if worker_count < 1 or frame_period_ns < 1:
        raise SfsInputError(
            f"worker_count and frame_period_ns must be >= 1, got {worker_count}, "
            f"{frame_period_ns}"
        )
    slot = (int(stamp_ns) - int(phase_ns) + frame_period_ns // 2) // frame_period_ns
    return slot % worker_count


#: Frames whose stamps set a :class:`FrameDealer`'s phase.
PHASE_FRAMES = 16


class FrameDealer:
    """Which worker solves each frame of a stream: :func:`frame_owner` at the stream's phase.

    The phase is the circular mean of the last :data:`PHASE_FRAMES` stamps
    modulo the period, so every worker that saw the same frames agrees on it
    (and it follows a camera whose true period differs slightly from
    ``frame_period_ns``). Frames then sit mid-slot, half a period from a
    boundary.

    Args:
        worker_count: workers sharing the stream, ≥ 1.
        frame_period_ns: the camera's frame period, ≥ 1.
    """

    def __init__(self, worker_count: int, frame_period_ns: int) -> None:
        frame_owner(0, worker_count, frame_period_ns)  # validates both
        self.worker_count = worker_count
        self.frame_period_ns = frame_period_ns
        self._angles: list[complex] = []

    def reset(self) -> None:
        """Forget the phase (a clock jump)."""
        self._angles.clear()

    @property
    def phase_ns(self) -> int:
        """Where in the period the stream's frames fall (0 before any frame)."""
        if not self._angles:
            return 0
        angle = float(np.angle(sum(self._angles)))
        return round(angle / (2.0 * math.pi) * self.frame_period_ns) % self.frame_period_ns

    def owner(self, stamp_ns: int, *, observe: bool = True) -> int:
        """The worker of the frame stamped ``stamp_ns``.

        observe: the stamp is a new input frame and joins the phase first
        (False for a stamp seen again, e.g. on another worker's output).
        """
        if observe:
            fraction = (int(stamp_ns) % self.frame_period_ns) / self.frame_period_ns
            self._angles.append(complex(math.cos(2.0 * math.pi * fraction),
                                        math.sin(2.0 * math.pi * fraction)))
            del self._angles[:-PHASE_FRAMES]
        return frame_owner(stamp_ns, self.worker_count, self.frame_period_ns, self.phase_ns)


def solution_from_depth(
    depth: np.ndarray,
    camera: CameraModel,
    options: SfsOptions,
    *,
    irradiance: np.ndarray | None = None,
) -> SfsSolution:
    """A solved frame rebuilt from its published depth (another worker's output).

    depth: (H, W) float32 relative depth, NaN invalid; irradiance: that
    frame's (H, W) input, if held (gives the solver's global shift). Only
    near-light. Returns an :class:`SfsSolution` on the solve grid of
    ``options`` whose node solution is the depth's ln r (the Newton seeds
    are then derived from the data, ``node_slope`` None).
    """
    if options.model != "near_light":
        raise SfsInputError("only near-light solutions warm-start another frame")
    grid = solve_grid(camera, "stereographic", options.solve_scale)
    log_r = log_distance_nodes(depth, grid)
    if irradiance is not None and np.shape(irradiance) == np.shape(depth):
        known = np.isfinite(irradiance)
        nodes, ok = grid.to_nodes(np.nan_to_num(irradiance), known)
        node_irradiance = np.where(ok, nodes, np.nan)
    else:
        node_irradiance = np.full(grid.shape, np.nan)
    return SfsSolution(
        depth=np.asarray(depth, dtype=np.float32),
        node_solution=log_r,
        node_irradiance=node_irradiance,
        grid=grid,
        valid=np.isfinite(depth),
        info=SolveInfo(0, 0.0, True, 0),
        model="near_light",
    )


@dataclass(frozen=True)
class _PeerDepth:
    """Another worker's published depth, rebuilt into a solution only if it is used."""

    depth: np.ndarray
    camera: CameraModel
    options: SfsOptions
    irradiance: np.ndarray | None


class WarmStartChain:
    """The newest solved frames of a stream and the warm start they give the next one.

    Args:
        predict: move the warm start by the camera motion when both poses
            are known (else use it as it stands).
        keep: solved frames kept, newest stamps first.
    """

    def __init__(self, *, predict: bool = True, keep: int = DEFAULT_KEEP) -> None:
        self.predict = predict
        self.keep = keep
        self._frames: dict[int, SfsSolution | _PeerDepth] = {}
        self._external_scale: float | None = None
        self._fitted_scale: float | None = None
        self._fitted_pairs: set[tuple[int, int]] = set()
        self.predicted = 0

    def reset(self) -> None:
        """Forget every solved frame (a camera change, a clock jump); the scale stays."""
        self._frames.clear()
        self._fitted_pairs.clear()

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def metres_per_unit(self) -> float | None:
        """The scale the translation is divided by: the caller's, else the fitted one."""
        return self._external_scale if self._external_scale is not None else self._fitted_scale

    def set_scale(self, metres_per_unit: float | None) -> None:
        """Use this scale (metres per depth_relative unit, e.g. endo_flow's); None: fit it."""
        if metres_per_unit is not None and not (
            math.isfinite(metres_per_unit) and metres_per_unit > 0.0
        ):
            metres_per_unit = None
        self._external_scale = metres_per_unit

    def add(self, stamp_ns: int, solution: SfsSolution) -> None:
        """Keep a frame this process solved."""
        if solution.model != "near_light":
            return
        self._keep(stamp_ns, solution)

    def add_depth(
        self,
        stamp_ns: int,
        depth: np.ndarray,
        camera: CameraModel,
        options: SfsOptions,
        *,
        irradiance: np.ndarray | None = None,
    ) -> None:
        """Keep another worker's solved frame: its (H, W) depth and, if held, its input.

        It is rebuilt on the solve grid (:func:`solution_from_depth`) only
        when it becomes a warm start.
        """
        if options.model != "near_light" or int(stamp_ns) in self._frames:
            return
        self._keep(stamp_ns, _PeerDepth(np.asarray(depth), camera, options, irradiance))

    def _keep(self, stamp_ns: int, frame: SfsSolution | _PeerDepth) -> None:
        self._frames[int(stamp_ns)] = frame
        while len(self._frames) > self.keep:
            del self._frames[min(self._frames)]

    def _solution(self, stamp_ns: int) -> SfsSolution:
        """The kept frame at ``stamp_ns`` as a solution (rebuilding another worker's)."""
        frame = self._frames[stamp_ns]
        if isinstance(frame, SfsSolution):
            return frame
        solution = solution_from_depth(
            frame.depth, frame.camera, frame.options, irradiance=frame.irradiance
        )
        own = [s for s, f in self._frames.items() if isinstance(f, SfsSolution)]
        if own:
            # The first-pass bookkeeping is the chain's, not the frame's.
            newest = self._frames[max(own)]
            assert isinstance(newest, SfsSolution)
            solution = dataclasses.replace(
                solution, ordered_work=newest.ordered_work,
                frames_since_ordered=newest.frames_since_ordered,
                ordered_retries=newest.ordered_retries,
            )
        self._frames[stamp_ns] = solution
        return solution

    def _base(self, stamp_ns: int) -> int | None:
        """The stamp of the kept frame to start from: the newest before, else the nearest."""
        if not self._frames:
            return None
        before = [s for s in self._frames if s < stamp_ns]
        if before:
            return max(before)
        return min(self._frames, key=lambda s: abs(s - stamp_ns))

    def _fit_scale(self, base: int, pose_at: PoseLookup) -> None:
        """Refine the fitted scale on the kept frame before ``base`` and ``base`` itself."""
        earlier = [s for s in self._frames if s < base]
        if not earlier or self._external_scale is not None:
            return
        pair = (max(earlier), base)
        if pair in self._fitted_pairs:
            return
        self._fitted_pairs.add(pair)
        first, second = pose_at(pair[0]), pose_at(pair[1])
        if first is None or second is None:
            return
        fit = estimate_metres_per_unit(
            self._solution(pair[0]), self._solution(pair[1]), relative_motion(first, second),
            initial=self._fitted_scale,
        )
        if fit is None:
            return
        if self._fitted_scale is None:
            self._fitted_scale = fit
        else:
            self._fitted_scale = float(np.exp(
                (1.0 - SCALE_UPDATE_WEIGHT) * np.log(self._fitted_scale)
                + SCALE_UPDATE_WEIGHT * np.log(fit)
            ))

    def warm_start(
        self, stamp_ns: int, pose_at: PoseLookup | None = None
    ) -> SfsSolution | PredictedStart | None:
        """The warm start of the frame stamped ``stamp_ns`` (None: solve it cold).

        pose_at: T_world_camera lookup by stamp (None, or a lookup that gives
        None for either frame: the kept frame as it stands).
        """
        base = self._base(int(stamp_ns))
        if base is None:
            return None
        solution = self._solution(base)
        if not self.predict or pose_at is None:
            return solution
        self._fit_scale(base, pose_at)
        before, now = pose_at(base), pose_at(int(stamp_ns))
        if before is None or now is None:
            return solution
        self.predicted += 1
        return predict_warm_start(
            solution, relative_motion(before, now), metres_per_unit=self.metres_per_unit
        )
