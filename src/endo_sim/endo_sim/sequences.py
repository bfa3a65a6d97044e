"""Recording plans: which scene, camera, motion, frames and tracker a run has.

:func:`build_sequence` turns a :class:`SimulationConfig` (what the CLI's
options say) into a :class:`Sequence`: the camera model, the renderer, the
frame times, the camera trajectory, the scene of each frame, and the
scene-specific ground truth. The bag writer and the live publisher both
consume a :class:`Sequence`, so offline bags and the live stand-in driver
show the same thing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from endo_io.camera import CameraModel
from endo_sim.abdomen import AbdomenGeometry, AbdomenScene
from endo_sim.colon import ColonGeometry, ColonScene
from endo_sim.errors import SimulationParameterError, UnknownSceneError
from endo_sim.graycard import DEFAULT_CARD_DISTANCE_M, GRAY_LEVELS, gray_card_scene
from endo_sim.handeye import (
    DEFAULT_INNER_CORNERS,
    DEFAULT_SQUARE_M,
    centred_board,
    handeye_stations,
    handeye_trajectory,
)
from endo_sim.photometry import Photometry
from endo_sim.render import Renderer
from endo_sim.surface import Scene
from endo_sim.texture import TextureOptions, tissue_texture
from endo_sim.tracker import TrackerModel
from endo_sim.trajectory import (
    NS_PER_S,
    AbdomenTrajectory,
    ColonTrajectory,
    StationTrajectory,
    Trajectory,
)

SCENES = ("colon", "abdomen", "graycard", "handeye")
#: Stamp of the first frame of an offline recording: 2026-11-22T00:00:00Z.
#: Fixed, never the wall clock, so that the same seed gives the same bytes.
DEFAULT_START_NS = 1_795_305_600 * NS_PER_S
OPTICAL_FRAME = "endoscope_optical_frame"


@dataclass(frozen=True)
class SimulationConfig:
    """Everything that defines a simulated recording.

    scene: one of :data:`SCENES`. width, height: image size (pixels).
    focal_px: focal length (None: width / 2, a 90° horizontal field of view).
    distortion: plumb_bob (k1, k2) radial coefficients. fov_radius_px:
    circular field of view (None: height / 2). fps, duration_s: frame rate
    and length (gray card: frames_per_level per card instead; hand–eye: set
    by the stations). channels: 1 (mono) or 3 (rgb8). depth_every: publish
    ground-truth depth with every n-th frame. seed: everything random.
    texture: the tissue albedo's amplitudes (colon and abdomen).
    """

    scene: str
    width: int = 640
    height: int = 480
    focal_px: float | None = None
    distortion: tuple[float, float] = (0.0, 0.0)
    fov_radius_px: float | None = None
    fps: float = 30.0
    duration_s: float = 10.0
    channels: int = 1
    seed: int = 0
    depth_every: int = 1
    photometry: Photometry = field(default_factory=Photometry)
    tracker: TrackerModel = field(default_factory=TrackerModel)
    texture: TextureOptions = field(default_factory=TextureOptions)
    frames_per_level: int = 10
    card_distance_m: float = DEFAULT_CARD_DISTANCE_M
    stations: int = 15
    dwell_s: float = 0.8
    move_s: float = 1.6
    start_ns: int = DEFAULT_START_NS

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise UnknownSceneError(
                f"unknown scene {self.scene!r}; choose one of {', '.join(SCENES)}"
            )
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise SimulationParameterError("image size must be 16..4096 pixels")
        if not 0.5 <= self.fps <= 240.0:
            raise SimulationParameterError("fps must be in [0.5, 240]")
        if not 0.0 < self.duration_s <= 3600.0:
            raise SimulationParameterError("duration must be in (0, 3600] s")
        if self.channels not in (1, 3):
            raise SimulationParameterError("channels must be 1 or 3")
        if self.depth_every < 1:
            raise SimulationParameterError("depth_every must be >= 1")
        if self.frames_per_level < 1 or self.stations < 3:
            raise SimulationParameterError("need >= 1 frame per gray level and >= 3 stations")
        if self.start_ns < 0:
            raise SimulationParameterError("start time must be >= 0")

    def camera(self) -> CameraModel:
        """The pinhole (+ radial distortion) camera model of the recording."""
        f = self.focal_px if self.focal_px is not None else 0.5 * self.width
        d = np.array([self.distortion[0], self.distortion[1], 0.0, 0.0, 0.0])
        return CameraModel.pinhole(
            self.width,
            self.height,
            f,
            f,
            0.5 * (self.width - 1),
            0.5 * (self.height - 1),
            D=d,
            distortion_model="plumb_bob",
            frame_id=OPTICAL_FRAME,
        )

    @property
    def fov_radius(self) -> float:
        """Radius of the circular field of view in pixels."""
        return self.fov_radius_px if self.fov_radius_px is not None else 0.5 * self.height


@dataclass(eq=False)
class Sequence:
    """A planned recording (see the module docstring).

    frame_times_ns: (N,) int64 since the start; scenes: the scenes shown;
    scene_index: (N,) int, which scene each frame shows; gray_levels: (N,)
    card reflectance per frame or None; ground_truth: scene-specific entries
    for the ground-truth YAML.
    """

    config: SimulationConfig
    camera: CameraModel
    renderer: Renderer
    trajectory: Trajectory
    frame_times_ns: np.ndarray
    scenes: list[Scene]
    scene_index: np.ndarray
    gray_levels: np.ndarray | None
    ground_truth: dict[str, Any]

    def scene_of_frame(self, k: int) -> Scene:
        """The scene frame ``k`` shows."""
        return self.scenes[int(self.scene_index[k])]

    @property
    def duration_ns(self) -> int:
        """Length of the recording (ns)."""
        return self.trajectory.duration_ns


def _frame_times(fps: float, count: int) -> np.ndarray:
    return np.round(np.arange(count) * (NS_PER_S / fps)).astype(np.int64)


def build_sequence(config: SimulationConfig) -> Sequence:
    """Plan the recording described by ``config`` (deterministic from its seed)."""
    camera = config.camera()
    renderer = Renderer(camera, config.photometry, config.fov_radius)
    seed = config.seed
    truth: dict[str, Any] = {"scene": config.scene, "seed": seed}
    gray_levels = None
    scenes: list[Scene]
    trajectory: Trajectory
    if config.scene in ("colon", "abdomen"):
        count = max(1, math.floor(config.duration_s * config.fps + 1e-9))
        duration_ns = round(count * NS_PER_S / config.fps)
        if config.scene == "colon":
            geometry = ColonGeometry()
            texture = tissue_texture(
                seed,
                (0.2, 2.0 * math.pi * geometry.radius_m),
                channels=config.channels,
                options=config.texture,
            )
            colon = ColonScene(geometry, texture, seed)
            scenes = [colon]
            trajectory = ColonTrajectory(colon, seed, duration_ns)
            truth["colon_geometry"] = dict(vars(geometry))
        else:
            ageometry = AbdomenGeometry()
            texture = tissue_texture(
                seed, (0.2, 0.2), channels=config.channels, options=config.texture
            )
            scenes = [AbdomenScene(ageometry, texture, seed)]
            trajectory = AbdomenTrajectory(ageometry.curvature_radius_m, seed, duration_ns)
            truth["abdomen_geometry"] = dict(vars(ageometry))
        frames = _frame_times(config.fps, count)
        scene_index = np.zeros(count, dtype=np.int64)
    elif config.scene == "graycard":
        count = len(GRAY_LEVELS) * config.frames_per_level
        duration_ns = round(count * NS_PER_S / config.fps)
        # The camera stays at the world origin: camera frame = world frame.
        trajectory = StationTrajectory(np.eye(4)[None], duration_ns, 1)
        scenes = [
            gray_card_scene(rho, config.card_distance_m, channels=config.channels)
            for rho in GRAY_LEVELS
        ]
        scene_index = np.repeat(np.arange(len(GRAY_LEVELS)), config.frames_per_level)
        gray_levels = np.array(GRAY_LEVELS)[scene_index]
        frames = _frame_times(config.fps, count)
        truth["gray_card"] = {
            "reflectances": [float(r) for r in GRAY_LEVELS],
            "frames_per_level": config.frames_per_level,
            "distance_m": float(config.card_distance_m),
            "normal_camera": [0.0, 0.0, -1.0],
            "T_world_camera": np.eye(4).tolist(),
        }
    else:
        board = centred_board(DEFAULT_INNER_CORNERS, DEFAULT_SQUARE_M, config.channels)
        stations = handeye_stations(board, camera, seed, config.stations, config.fov_radius)
        moves = handeye_trajectory(stations, config.dwell_s, config.move_s)
        trajectory = moves
        count = max(1, math.floor(trajectory.duration_ns * config.fps / NS_PER_S + 1e-9))
        frames = _frame_times(config.fps, count)
        scenes = [board]
        scene_index = np.zeros(count, dtype=np.int64)
        truth["checkerboard"] = {
            "inner_corners": list(board.inner_corners),
            "square_m": float(board.square_m),
            "dark_albedo": float(board.dark),
            "light_albedo": float(board.light),
            "margin_squares": float(board.margin_squares),
            "T_world_board": board.pose_world_board.tolist(),
            "corners_world_m": board.corners_world().tolist(),
        }
        truth["stations"] = {
            "T_world_camera": stations.tolist(),
            "dwell_intervals_s": (moves.station_times_ns() / NS_PER_S).tolist(),
        }
    return Sequence(
        config, camera, renderer, trajectory, frames, scenes, scene_index, gray_levels, truth
    )
