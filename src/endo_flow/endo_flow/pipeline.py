"""The per-frame step of endo_flow: tracks + poses -> scale -> metric depth, world points, map.

:class:`FlowPipeline` is the one implementation that the ``endo-flow`` node
and the offline processor both call, one :class:`FlowFrame` at a time, in
stamp order:

1. **Track** features by Lucas–Kanade on the corrected image
   (:mod:`endo_flow.tracking`).
2. With a pose, **triangulate** every track over its keyframe views and the
   current one (:mod:`endo_flow.keyframes`, :mod:`endo_flow.triangulation`).
3. **Observe the scale**: ln(z / d_rel) at the accepted tracks' current
   pixels, one robust observation per frame (:func:`endo_flow.scale.observe_scale`),
   fused by the Kalman filter on ln s (:class:`endo_flow.scale.ScaleFilter`).
4. Optionally fit the **shape correction** field to the residuals
   (:mod:`endo_flow.shape_correction`).
5. Once the scale is usable: **metric depth** = s · e^c · d_rel, the
   **world points** (``CameraModel.depth_to_points`` on a binned model of
   the same camera, then :func:`endo_io.pose.transform_points`), their grey
   level and normals, and the **voxel map** update. One back-projection
   gives both clouds (:func:`endo_flow.cloud.world_clouds`): the output's,
   every ``cloud_decimation``-th pixel (the live topic's), and the map's,
   every ``map_decimation``-th (1: full resolution) on every
   ``map_every``-th frame with world points.

Without a pose (a tracker dropout) the tracks continue and the depth is made
metric with the held scale, but nothing is triangulated and no world point
is produced. A frame stamped before the previous one (a looped bag) resets
every buffer, the filter, the shape correction and the map, and raises
:class:`endo_io.errors.ClockJumpError`; the next frame starts afresh.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from endo_flow.cloud import BandedCloud, Cloud, binned_camera, world_clouds
from endo_flow.errors import FlowInputError, NoFeaturesError
from endo_flow.keyframes import Keyframe, KeyframeWindow, TrackViews
from endo_flow.pose_smoothing import PoseSmoother
from endo_flow.reprojection import REFERENCES, fit_log_scale, track_leverage
from endo_flow.scale import (
    ScaleEstimate,
    ScaleFilter,
    ScaleFilterOptions,
    ScaleObservation,
    ScaleState,
    ViewNovelty,
    observe_log_ratios,
    view_weights,
)
from endo_flow.shape_correction import ShapeCorrectionOptions, ShapeCorrector
from endo_flow.tracking import FeatureTracker, TrackingOptions
from endo_flow.triangulation import TriangulationGates, triangulate
from endo_flow.voxel_map import VoxelMap
from endo_io.camera import CameraModel
from endo_io.errors import ClockJumpError, PoseError
from endo_io.pose import check_rotation

#: How a track's parallax is gated: its rays' widest angle, the angle predicted
#: from the poses and SFS's depth (:func:`geometric_parallax`) or from the
#: baseline alone, or not at all (the rays only guarded against being parallel).
PARALLAX_GATES = ("rays", "geometric", "baseline", "none")
#: How a frame observes ln s: the triangulated tracks' ln(z / d_rel), or the
#: scale-only reprojection fit (:mod:`endo_flow.reprojection`).
SCALE_OBSERVATIONS = ("triangulation", "reprojection")
#: The rays' parallax gate when the predicted parallax is gated (parallel rays).
RAY_PARALLAX_GUARD_RAD = float(np.radians(1.0))


@dataclass(frozen=True)
class FlowOptions:
    """Every setting of :class:`FlowPipeline`.

    Attributes:
        tracking: feature tracking (:class:`~endo_flow.tracking.TrackingOptions`).
        gates: triangulation acceptance (:class:`~endo_flow.triangulation.TriangulationGates`).
        scale: the scale filter (:class:`~endo_flow.scale.ScaleFilterOptions`).
        shape: the shape correction
            (:class:`~endo_flow.shape_correction.ShapeCorrectionOptions`).
        keyframes: keyframes kept per track window.
        keyframe_step_m: camera motion that makes a new keyframe, metres.
        keyframe_turn_deg: camera rotation that also does, degrees.
        keyframe_max_age_s: keyframes older than this are dropped, seconds.
        pose_smoothing_s: half-width of the local linear regression that
            smooths the keyframes' poses (:mod:`endo_flow.pose_smoothing`),
            seconds; 0 uses the raw poses.
        pose_noise_m: the camera-centre noise of one pose (tracker noise and
            its lever arm to the camera), metres; sets the part of a frame's
            scale error that its points share.
        shared_error_frames: the number of consecutive observations that
            share one draw of the keyframes' pose errors; the shared term
            ``pose_noise_m / baseline`` of an observation's variance is
            counted this many times, since the filter fuses every frame as
            independent (an effective sample size: the observations' lag-one
            autocorrelation is 0.5–0.9 on the evaluation bags, (1 + ρ) /
            (1 − ρ) = 3–19 frames). It weights the small-baseline
            observations of the first second down against the later ones
            and makes the filter converge on more than one draw of the
            pose errors. 1 (the default) fuses the frames as independent;
            4 with ``pose_smoothing_s`` 0.5 and ``scale.converged_std``
            0.045 was measured (docs/flow.md): better on the bags it was
            chosen on, not on two held-out renders, so not the default.
        observation_floor: least standard deviation of one frame's ln s
            observation (the frames' errors are correlated).
        max_view_spread: a track's ln(z_k / d_rel_k) over its views k (the
            triangulated point's depth in each view against that view's
            depth_relative) must have a standard deviation at most this:
            a track that slides over the surface (an occluding fold edge,
            shading that moves with the light) triangulates to a point that
            the SFS surfaces of its views do not agree on.
        exposure_jump: a frame whose tracked points all brighten or darken
            by more than this (ln of the median ratio to the previous frame)
            had its exposure, gain or light power changed: ρ changed by
            that ratio g, so s is multiplied by √g at once (near-light SFS
            depth goes as 1/√ρ); camera motion changes the ratio by a few
            percent per frame at most.
        min_observation_points: fewer accepted tracks give no observation.
        max_parallax_weight_deg: parallax beyond this gets no more weight.
        parallax_gate: ``rays``: ``gates.min_parallax_rad`` applies to the
            widest angle between a track's rays; ``geometric``: to the
            angle the track's baseline subtends at SFS's depth
            (:func:`geometric_parallax`), the rays only guarded against
            being parallel (1°). A gate on the rays' own angle keeps the
            tracks whose noise widened it, which triangulate too near: the
            observations of the first, small-baseline second are biased low
            (true poses, phantom: max error after convergence 3.85 % →
            1.23 %). Measured, not the default: with the tracker's noise it
            is worse on the phantom and the textured abdomen (docs/flow.md).
            ``baseline``: the same angle with every track at the frame's
            median distance, so the gate follows the track's baseline only
            and chooses neither by triangulation nor by SFS error (the
            geometric gate keeps tracks where SFS reads near): phantom
            4.75 → 2.69 %, colon seed 2 4.41 → 4.12 %, held-out colon seed 3
            6.17 → 3.77 %, the abdomens +0.1–0.16 %; not the default only
            because the still-camera test's mean comes out at +2.03 % (bar
            2 %). ``none``: no parallax gate (the rays only guarded against
            being parallel, 1°), for the reprojection fit, where a track
            with little parallax has little leverage by itself.
        scale_observation: ``triangulation``: a frame's ln s is the robust
            location of its triangulated tracks' ln(z / d_rel) (weighted
            by parallax², see ``observation_views``); ``reprojection``: the
            one ln s that best reprojects SFS's points, scaled, from each
            track's reference views into its other views
            (:func:`endo_flow.reprojection.fit_log_scale`, robust
            Gauss–Newton over every track and view of the window at once;
            its start is the triangulated median). Measured, not the
            default (docs/flow.md): better on the colons (seed 2 4.41 →
            1.13 %, held-out seed 3 6.05 → 3.44 %), worse on the phantom,
            the abdomens and held-out matte seed 5; the tracker's pose
            noise, which every track of a frame shares, dominates either.
        reprojection_reference: which views of a track are references in
            the reprojection fit: ``all`` (each in turn) or ``newest``.
        reprojection_views: the views the reprojection fit uses: ``all``
            (the keyframes and the current frame, every frame) or
            ``keyframes`` (their smoothed poses only, the current frame's
            raw pose left out; one observation per change of the window,
            since frames between keyframes would repeat it). Measured, not
            the default (docs/flow.md): with the rays' gate and
            ``scale.converged_std`` 0.035, max error after convergence
            phantom 4.75 → 4.57 %, colon seed 2 4.41 → 3.71 %, matte seeds
            3 / 4 2.64 / 2.70 → 2.02 / 1.39 %, textured abdomen 5.15 →
            5.18 %; held out colon seed 3 6.05 → 3.93 %, matte seed 5
            10.18 → 10.72 %.
        observation_rings, observation_sectors: a frame's tracks are
            weighted so that each of ``observation_rings`` equal-area rings
            of the field of view, cut into ``observation_sectors`` sectors,
            counts alike (:func:`area_balanced_weights`); 1 and 1 keep the
            parallax weights alone.
        novelty_floor: below 1, each observation is fused with its
            variance divided by its novelty, the share of its weight on
            views no earlier observation used
            (:class:`~endo_flow.scale.ViewNovelty`), at least this; 1 (the
            default) fuses every frame as independent. Measured and not
            the default (docs/flow.md): with ``scale.converged_std`` 0.05
            it halves the excursions after convergence on the phantom and
            the matte abdomen but keeps an early wild observation longer
            (rendered test frames with tracker noise: worse at 1.5 s on 5
            of 8 seeds).
        min_features: a frame with fewer features raises NoFeaturesError.
        cloud_decimation: the output's world cloud (the live topic's) takes
            every n-th pixel along each axis.
        cloud_min_depth_m, cloud_max_depth_m: depth range of cloud points.
        map_enabled: fuse world points into the voxel map.
        map_decimation: the map fuses every n-th pixel along each axis (1:
            full resolution), from the same back-projection as the output's
            cloud.
        map_every: the map fuses the points of every n-th frame that has
            world points (1: every frame); the CPU knob of the live map
            (docs/flow.md), where a coarser grid would lose resolution.
        voxel_size_m: voxel edge of the map, metres.
        max_voxels: capacity of the map (memory bound).
    """

    tracking: TrackingOptions = field(default_factory=TrackingOptions)
    gates: TriangulationGates = field(default_factory=TriangulationGates)
    scale: ScaleFilterOptions = field(default_factory=ScaleFilterOptions)
    shape: ShapeCorrectionOptions = field(
        default_factory=lambda: ShapeCorrectionOptions(mode="none")
    )
    keyframes: int = 30
    keyframe_step_m: float = 0.8e-3
    keyframe_turn_deg: float = 2.0
    keyframe_max_age_s: float = 4.0
    pose_smoothing_s: float = 0.3
    pose_noise_m: float = 0.5e-3
    shared_error_frames: float = 1.0
    observation_floor: float = 0.03
    max_view_spread: float = 0.05
    exposure_jump: float = 0.08
    min_observation_points: int = 8
    max_parallax_weight_deg: float = 20.0
    parallax_gate: str = "rays"
    scale_observation: str = "triangulation"
    reprojection_reference: str = "all"
    reprojection_views: str = "all"
    observation_rings: int = 4
    observation_views: str = "all"
    observation_sectors: int = 1
    novelty_floor: float = 1.0
    min_features: int = 8
    cloud_decimation: int = 4
    cloud_min_depth_m: float = 1e-3
    cloud_max_depth_m: float = 0.3
    map_enabled: bool = True
    map_decimation: int = 1
    map_every: int = 1
    voxel_size_m: float = 1e-3
    max_voxels: int = 2_000_000

    def __post_init__(self) -> None:
        if self.keyframes < 2 or self.keyframe_max_age_s <= 0.0:
            raise ValueError("keyframes must be >= 2 and keyframe_max_age_s > 0")
        if self.keyframe_step_m < 0.0 or self.keyframe_turn_deg < 0.0:
            raise ValueError("keyframe_step_m and keyframe_turn_deg must be >= 0")
        if self.pose_smoothing_s < 0.0:
            raise ValueError("pose_smoothing_s must be >= 0")
        if self.pose_noise_m < 0.0 or self.observation_floor < 0.0:
            raise ValueError("pose_noise_m and observation_floor must be >= 0")
        if not (self.max_view_spread > 0.0 and self.exposure_jump > 0.0):
            raise ValueError("max_view_spread and exposure_jump must be > 0")
        if self.min_observation_points < 1 or self.min_features < 0:
            raise ValueError("min_observation_points must be >= 1, min_features >= 0")
        if self.parallax_gate not in PARALLAX_GATES:
            raise ValueError(f"parallax_gate must be one of {PARALLAX_GATES}")
        if self.scale_observation not in SCALE_OBSERVATIONS:
            raise ValueError(f"scale_observation must be one of {SCALE_OBSERVATIONS}")
        if self.reprojection_views not in ("all", "keyframes"):
            raise ValueError("reprojection_views must be all or keyframes")
        if self.reprojection_reference not in REFERENCES:
            raise ValueError(f"reprojection_reference must be one of {REFERENCES}")
        if self.shared_error_frames < 1.0:
            raise ValueError("shared_error_frames must be >= 1")
        if not self.max_parallax_weight_deg > 0.0:
            raise ValueError("max_parallax_weight_deg must be > 0")
        if not 0.0 < self.novelty_floor <= 1.0:
            raise ValueError("novelty_floor must be in (0, 1]")
        if self.observation_rings < 1 or self.observation_sectors < 1:
            raise ValueError("observation_rings and observation_sectors must be >= 1")
        if self.cloud_decimation < 1 or self.map_decimation < 1:
            raise ValueError("cloud_decimation and map_decimation must be >= 1")
        if self.map_every < 1:
            raise ValueError("map_every must be >= 1")
        if not 0.0 <= self.cloud_min_depth_m < self.cloud_max_depth_m:
            raise ValueError("need 0 <= cloud_min_depth_m < cloud_max_depth_m")
        if not self.voxel_size_m > 0.0 or self.max_voxels < 1:
            raise ValueError("voxel_size_m must be > 0 and max_voxels >= 1")


@dataclass(frozen=True)
class FlowFrame:
    """One synchronised input frame.

    Attributes:
        stamp_ns: the image stamp, integer ns.
        image: (H, W) float32 corrected linear irradiance (``endo_calib``
            output), NaN outside the field of view and where saturated.
        depth_relative: (H, W) float32 relative depth along z
            (``endo_sfs`` output), NaN invalid.
        camera: the camera model of both images.
        T_world_camera: (4, 4) float64 camera pose at ``stamp_ns``
            (``/endoscope/pose``, metres), or None when there is none.
    """

    stamp_ns: int
    image: np.ndarray
    depth_relative: np.ndarray
    camera: CameraModel
    T_world_camera: np.ndarray | None


@dataclass(frozen=True)
class FlowDiagnostics:
    """Per-frame counters and figures.

    Attributes:
        has_pose: the frame had a pose.
        keyframe: the frame became a keyframe.
        tracks: features tracked in the frame.
        seeded: of those, new this frame.
        lost: tracks of the previous frame not continued.
        keyframes: keyframes held.
        triangulated: tracks that passed the triangulation gates.
        observation: this frame's observed s (NaN: none).
        observation_std: its ln standard deviation (NaN: none).
        observation_points: points in that observation.
        accepted: the observation entered the filter.
        gated: the observation was rejected as an outlier.
        step: the observation completed a detected scale step.
        exposure_step: the image brightness jumped (exposure or gain
            change); the scale was multiplied by the square root of the jump.
        brightness_ratio: median brightness of the tracked points over the
            previous frame's.
        shape_correction: the shape correction field was applied.
        cloud_points: world points produced (the output's cloud).
        map_points: points fused into the map this frame (0 when the map
            did not take this frame).
        timings_ms: wall time per stage, milliseconds (tracking,
            triangulation, scale, depth, cloud, map).
    """

    has_pose: bool
    keyframe: bool
    tracks: int
    seeded: int
    lost: int
    keyframes: int
    triangulated: int
    observation: float
    observation_std: float
    observation_points: int
    accepted: bool
    gated: bool
    step: bool
    exposure_step: bool
    brightness_ratio: float
    shape_correction: bool
    cloud_points: int
    map_points: int
    timings_ms: dict[str, float]


@dataclass(frozen=True)
class FlowOutput:
    """What one frame produced.

    Attributes:
        stamp_ns: the frame's stamp, integer ns.
        depth: (H, W) float32 metric depth along z, metres, NaN invalid
            (REP 118), or None while the scale is not usable yet (the filter
            has not converged once: ``scale.usable`` is False).
        points: (N, 3) float32 world points of the depth, every
            ``cloud_decimation``-th pixel, metres (empty without depth or
            without a pose).
        intensity: (N,) uint8 grey level of those points (the tracking
            image's 8-bit mapping).
        normals: (N, 3) float32 unit world normals facing the camera (NaN
            where the neighbours were missing).
        scale: the scale estimate after this frame.
        triangulated: (M, 3) float64 world points of this frame's accepted
            tracks (the metric evidence), metres.
        diagnostics: per-frame counters.
    """

    stamp_ns: int
    depth: np.ndarray | None
    points: np.ndarray
    intensity: np.ndarray
    normals: np.ndarray
    scale: ScaleEstimate
    triangulated: np.ndarray
    diagnostics: FlowDiagnostics


def sample_bilinear(image: np.ndarray, uv: np.ndarray, max_ratio: float = 1.1) -> np.ndarray:
    """Bilinear samples of a depth image at sub-pixel positions.

    Args:
        image: (H, W) float, NaN invalid.
        uv: (N, 2) float pixels (u right, v down, centres at integers).
        max_ratio: if the four neighbours' largest/smallest exceeds this (a
            depth edge), the sample is NaN.

    Returns:
        (N,) float64, NaN outside the image, next to an invalid pixel or
        across an edge.
    """
    h, w = image.shape
    u, v = uv[:, 0], uv[:, 1]
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 < w) & (v0 + 1 < h)
    out = np.full(len(uv), np.nan)
    if not np.any(inside):
        return out
    u0, v0, fu, fv = u0[inside], v0[inside], (u - u0)[inside], (v - v0)[inside]
    corners = np.stack([image[v0, u0], image[v0, u0 + 1], image[v0 + 1, u0],
                        image[v0 + 1, u0 + 1]], axis=1).astype(np.float64)
    value = (corners[:, 0] * (1 - fu) * (1 - fv) + corners[:, 1] * fu * (1 - fv)
             + corners[:, 2] * (1 - fu) * fv + corners[:, 3] * fu * fv)
    with np.errstate(invalid="ignore", divide="ignore"):
        edge = corners.max(axis=1) > max_ratio * corners.min(axis=1)
    value[edge | ~np.isfinite(value)] = np.nan
    out[inside] = value
    return out


def area_balanced_weights(
    uv: np.ndarray,
    weights: np.ndarray,
    centre: tuple[float, float],
    radius_px: float,
    *,
    rings: int,
    sectors: int = 1,
) -> np.ndarray:
    """Reweight points so that each zone of the field of view counts by its area.

    The image is split into ``rings`` concentric rings of equal area (radii
    R·√(k / rings)) around ``centre``, each cut into ``sectors`` equal
    angular sectors; within a zone the points keep their relative weights,
    and every zone that holds points gets the same total. SFS's depth errors
    vary over the image (mostly with the radius: the light model, the
    near-light fall-off), so a scale observed where the tracks happen to be
    (the rim in forward motion, where the parallax is) follows the tracks'
    distribution; balanced over equal areas it estimates the scale that fits
    the whole image, which is what the oracle (and the depth image) needs.

    Args:
        uv: (N, 2) float pixels.
        weights: (N,) float >= 0 weights of the points.
        centre: (cx, cy) pixel of the rings' centre.
        radius_px: radius of the field of view, pixels (points beyond it
            fall in the outer ring).
        rings: number of rings (1 with ``sectors`` 1: the weights unchanged).
        sectors: angular sectors per ring.

    Returns:
        (N,) float64 weights, summing to the number of zones with points.
    """
    w = np.asarray(weights, np.float64)
    if rings * sectors <= 1 or len(w) == 0:
        return w
    p = np.asarray(uv, np.float64)
    dx, dy = p[:, 0] - centre[0], p[:, 1] - centre[1]
    rho2 = (dx * dx + dy * dy) / radius_px**2
    ring = np.minimum((rho2 * rings).astype(np.int64), rings - 1)
    sector = np.minimum(((np.arctan2(dy, dx) + np.pi) / (2 * np.pi) * sectors).astype(np.int64),
                        sectors - 1)
    zone = ring * sectors + sector
    total = np.bincount(zone, weights=w, minlength=rings * sectors)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = w / total[zone]
    out[~np.isfinite(out)] = 0.0
    return out


def geometric_parallax(views: TrackViews, selected: np.ndarray, log_ratio_now: np.ndarray,
                       relative_now: np.ndarray, optical_axis: np.ndarray, *,
                       one_distance: bool = False) -> np.ndarray:
    """Each selected track's parallax predicted from the poses and SFS, not from its own rays.

    The angle that the baseline between a track's oldest view and the current
    one subtends at the distance SFS gives it (depth_relative times the
    frame's median ln ratio, one constant for every track):
    atan(|b × d| / range), d the current ray. The rays' own parallax carries
    the track's error (LK noise, the views' pose errors): a track seen with
    too wide an angle triangulates too near, so a gate on that angle keeps
    the near-biased tracks close to the threshold and drops
    the far-biased ones (ln s biased low by a few percent while the
    baselines are short); a gate on this angle is blind to the track's own
    error.

    Args:
        views: (N, V) views, oldest first; the current view last.
        selected: (N,) bool, the tracks wanted (M of them).
        log_ratio_now: (M,) float ln(z / d_rel) of those tracks in the current view.
        relative_now: (M,) float their depth_relative in the current view.
        optical_axis: (3,) world optical axis of the current view.
        one_distance: every track at the frame's median distance (the
            angle then follows the baseline's geometry only: a gate on it
            chooses tracks neither by their triangulation error nor by
            SFS's, which a gate on SFS's near regions would).

    Returns:
        (M,) float64 predicted parallax, radians.
    """
    valid = views.valid[selected]
    centres = np.broadcast_to(views.centres, (*views.valid.shape, 3))[selected]
    directions = views.directions[selected]
    rows = np.arange(len(valid))
    first = np.argmax(valid, axis=1)
    last = valid.shape[1] - 1 - np.argmax(valid[:, ::-1], axis=1)
    baseline = centres[rows, last] - centres[rows, first]
    ray = directions[rows, last]
    perpendicular = np.linalg.norm(np.cross(baseline, ray), axis=1)
    scale = float(np.exp(np.nanmedian(log_ratio_now)))
    with np.errstate(invalid="ignore", divide="ignore"):
        distance = scale * relative_now / np.maximum(ray @ np.asarray(optical_axis), 1e-3)
        if one_distance:
            distance = np.full_like(distance, np.nanmedian(distance))
        angle = np.arctan2(perpendicular, distance)
    return np.where(np.isfinite(angle), angle, 0.0)


def column_nanmedian(values: np.ndarray) -> np.ndarray:
    """Median of each column of a (N, V) float array over its finite entries (NaN if none).

    ``np.nanmedian(values, axis=0)`` on small arrays goes through masked
    arrays and costs ~1 ms per frame here; one sort (NaN last) does it.
    """
    if len(values) == 0:
        return np.full(values.shape[1], np.nan)
    ordered = np.sort(values, axis=0)
    count = np.isfinite(ordered).sum(axis=0)
    columns = np.arange(values.shape[1])
    lo = ordered[np.maximum(count - 1, 0) // 2, columns]
    hi = ordered[np.minimum(count // 2, len(values) - 1), columns]
    out = 0.5 * (lo + hi)
    out[count == 0] = np.nan
    return out


def view_log_ratios(views: TrackViews, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per track and view, ln(z_k / d_rel_k); and per track its spread over the views.

    z_k is the depth of the triangulated point along view k's optical axis,
    d_rel_k the depth_relative sampled at the track in view k. A static point
    on the surface has the same ratio in every view, up to the view's own
    scale (a gain step changes every ratio of a view alike), so each view's
    median over the tracks is removed before the spread is taken.

    Args:
        views: (N, V) views with ``axes`` and ``relative``.
        points: (N, 3) triangulated world points (NaN rows allowed).

    Returns:
        ((N, V) float64 ln ratios, NaN where unknown; (N,) float64 standard
        deviation over a track's views after removing each view's median,
        NaN with fewer than two views).
    """
    assert views.axes is not None and views.relative is not None
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.einsum("nvi,nvi->nv", points[:, None, :] - views.centres, views.axes)
        values = np.log(z) - np.log(views.relative)
    values[~views.valid] = np.nan
    ok = np.isfinite(values)
    count = ok.sum(axis=1)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN views
        centred = values - column_nanmedian(values)
        spread = np.nanstd(centred, axis=1, ddof=1)
    spread[count < 2] = np.nan
    return values, spread


class FlowPipeline:
    """The per-frame step (see the module docstring).

    Args:
        options: every setting (defaults if None).
    """

    def __init__(self, options: FlowOptions | None = None) -> None:
        self.options = options or FlowOptions()
        opts = self.options
        self.tracker = FeatureTracker(opts.tracking)
        self.window = KeyframeWindow(
            opts.keyframes, opts.keyframe_step_m, float(np.radians(opts.keyframe_turn_deg)),
            round(opts.keyframe_max_age_s * 1e9),
        )
        self.scale_filter = ScaleFilter(opts.scale)
        # with the geometric parallax gate the rays' own parallax only guards
        # against degenerate (parallel) rays
        self._ray_gates = (opts.gates if opts.parallax_gate == "rays" else dataclasses.replace(
            opts.gates, min_parallax_rad=min(opts.gates.min_parallax_rad, RAY_PARALLAX_GUARD_RAD)))
        self.novelty = ViewNovelty(opts.novelty_floor)
        self.smoother = PoseSmoother(round(opts.pose_smoothing_s * 1e9),
                                     capacity=2048)
        self.voxel_map = VoxelMap(opts.voxel_size_m, opts.max_voxels) if opts.map_enabled else None
        self._shape: ShapeCorrector | None = None
        self._camera: CameraModel | None = None
        self._map_turn = 0  # frames with world points so far: the map takes every map_every-th
        # the map cloud of a frame process(defer_map=True) left for fuse_deferred_map(), and
        # whether a band of it is in the map (the next bands continue that insert)
        self._deferred_map: BandedCloud | None = None
        self._deferred_started = False
        self._last_stamp_ns: int | None = None
        self._observed_version = -1  # the window's version at the last keyframes-only fit
        self.frames = 0
        self.resets = 0
        self.camera_changes = 0

    @property
    def scale(self) -> ScaleEstimate:
        """The current scale estimate."""
        return self.scale_filter.estimate

    @property
    def shape_corrector(self) -> ShapeCorrector | None:
        """The shape correction state (None before the first frame)."""
        return self._shape

    def reset(self) -> None:
        """Forget tracks, keyframes, the scale, the shape correction and the map."""
        self.tracker.reset()
        self.window.clear()
        self.smoother.clear()
        self.scale_filter.reset()
        self.novelty.reset()
        if self._shape is not None:
            self._shape.reset()
        if self.voxel_map is not None:
            self.voxel_map.reset()
        self._map_turn = 0
        self._deferred_map = None
        self._last_stamp_ns = None
        self.resets += 1

    @property
    def map_pending(self) -> bool:
        """Whether rows of a deferred map frame wait for :meth:`fuse_deferred_map`."""
        return self._deferred_map is not None

    def reset_map(self) -> int:
        """Empty the map and drop a frame waiting for it; returns the voxels dropped."""
        self._deferred_map = None
        if self.voxel_map is None:
            return 0
        dropped = len(self.voxel_map)
        self.voxel_map.reset()
        return dropped

    def set_cloud_options(self, **changes: int) -> None:
        """Change ``cloud_decimation``, ``map_decimation`` or ``map_every``; state is kept.

        Raises:
            ValueError: another field, or a value FlowOptions refuses.
        """
        allowed = {"cloud_decimation", "map_decimation", "map_every"}
        if not set(changes) <= allowed:
            raise ValueError(f"only {sorted(allowed)} change on the fly, not "
                             f"{sorted(set(changes) - allowed)}")
        values: dict[str, Any] = {name: int(value) for name, value in changes.items()}
        self.options = dataclasses.replace(self.options, **values)

    def _keyframe_pose(self, keyframe: Keyframe) -> np.ndarray:
        try:
            return self.smoother.smoothed(keyframe.stamp_ns)
        except KeyError:  # older than the smoother holds
            return keyframe.T_world_camera

    def _check(self, frame: FlowFrame) -> np.ndarray | None:
        cam = frame.camera
        size = (cam.height, cam.width)
        for name, array in (("image", frame.image), ("depth_relative", frame.depth_relative)):
            shape = np.shape(array)
            if shape != size:
                raise FlowInputError(
                    f"{name} is {shape[1] if len(shape) > 1 else '?'}x{shape[0] if shape else '?'}"
                    f" but camera_info is {cam.width}x{cam.height}"
                )
            if not np.issubdtype(np.asarray(array).dtype, np.floating):
                raise FlowInputError(f"{name} must be float, got {np.asarray(array).dtype}")
        if frame.T_world_camera is None:
            return None
        T = np.asarray(frame.T_world_camera, np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise PoseError(f"pose at {frame.stamp_ns} ns is not a finite (4, 4) transform")
        check_rotation(T[:3, :3])
        return T

    def _prepare(self, camera: CameraModel) -> None:
        if self._camera is not None and self._camera == camera:
            return
        if self._camera is not None:
            # another camera (a new resolution mid-stream): the tracks and the
            # keyframes' pixels belong to the old one; the scale and the map stay
            self.tracker.reset()
            self.window.clear()
            self.camera_changes += 1
        self._camera = camera
        radius = 0.5 * min(camera.width, camera.height)
        self._shape = ShapeCorrector(camera.width, camera.height, (camera.cx, camera.cy), radius,
                                     self.options.shape)

    def process(self, frame: FlowFrame, *, defer_map: bool = False) -> FlowOutput:
        """Run the per-frame step on one frame (frames in stamp order).

        With ``defer_map`` a frame the map takes (every ``map_every``-th with
        world points) is not fused here: :meth:`fuse_deferred_map` does it,
        after the caller has published the output, whole or in bands over the
        next frames (the live node: the full-resolution cloud and its insert,
        ~15-30 ms, then no longer delay that frame's cloud nor any one
        frame). The map is the same either way (tested); what is left of a
        frame when the next frame the map takes comes is fused first.

        Raises:
            FlowInputError: image or depth_relative of another size than the
                camera, or not float; a repeated stamp.
            PoseError: a pose that is not a finite rigid transform.
            NoFeaturesError: fewer than ``min_features`` features (a
                textureless or black frame); the frame is dropped.
            ClockJumpError: the stamp is before the previous frame's; every
                state was reset and this frame is dropped.
        """
        opts = self.options
        T = self._check(frame)
        if self._last_stamp_ns is not None and frame.stamp_ns <= self._last_stamp_ns:
            if frame.stamp_ns == self._last_stamp_ns:
                raise FlowInputError(f"frame stamp {frame.stamp_ns} ns repeats the previous one")
            back = (self._last_stamp_ns - frame.stamp_ns) / 1e9
            self.reset()
            raise ClockJumpError(
                f"frame time jumped back {back:.3f} s; tracks, keyframes, scale filter, shape "
                "correction and map reset"
            )
        self._last_stamp_ns = frame.stamp_ns
        self._prepare(frame.camera)
        assert self._shape is not None and self._camera is not None
        camera = frame.camera
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        features = self.tracker.track(frame.image)
        timings["tracking"] = 1e3 * (time.perf_counter() - t0)
        self.frames += 1
        if len(features.ids) < opts.min_features:
            self.scale_filter.predict(frame.stamp_ns)
            raise NoFeaturesError(
                f"{len(features.ids)} trackable features (need {opts.min_features}): textureless,"
                f" black or saturated frame ({100 * features.valid_fraction:.0f} % valid pixels)"
            )

        exposure_step = bool(np.isfinite(features.brightness_ratio) and abs(
            np.log(features.brightness_ratio)) > opts.exposure_jump)
        if exposure_step:
            self.scale_filter.rescale(0.5 * np.log(features.brightness_ratio))
            # depth_relative goes as 1/√ρ: the kept views' samples follow the step
            self.window.scale_relative(float(features.brightness_ratio) ** -0.5)
        t0 = time.perf_counter()
        observation: ScaleObservation | None = None
        triangulated = np.empty((0, 3))
        n_accepted = 0
        is_keyframe = False
        update = None
        if T is not None:
            rays = camera.pixels_to_rays(features.uv)
            relative_now = sample_bilinear(frame.depth_relative, features.uv)
            # the shape correction as it stands now goes with each view's sample
            corrected_now = relative_now * np.exp(self._shape.log_correction(features.uv))
            current = Keyframe(frame.stamp_ns, T, features.ids, rays, corrected_now)
            self.smoother.add(frame.stamp_ns, T)
            views = self.window.views(features.ids, current, self._keyframe_pose)
            result = triangulate(views, self._ray_gates, optical_axis=T[:3, 2])
            timings["triangulation"] = 1e3 * (time.perf_counter() - t0)
            t0 = time.perf_counter()
            log_ratio, spread = view_log_ratios(views, result.points)
            accepted = result.accepted & (spread <= opts.max_view_spread)
            accepted &= np.isfinite(log_ratio[:, -1])  # the current view has depth_relative
            if opts.parallax_gate in ("geometric", "baseline") and accepted.any():
                predicted = geometric_parallax(views, accepted, log_ratio[accepted, -1],
                                               relative_now[accepted], T[:3, 2],
                                               one_distance=opts.parallax_gate == "baseline")
                chosen = np.flatnonzero(accepted)
                accepted[chosen[predicted < opts.gates.min_parallax_rad]] = False
            n_accepted = int(accepted.sum())
            triangulated = result.points[accepted]
            if n_accepted >= opts.min_observation_points:
                cap = np.radians(opts.max_parallax_weight_deg)
                weights = np.minimum(result.parallax_rad[accepted], cap) ** 2
                if opts.observation_rings > 1 or opts.observation_sectors > 1:
                    weights = area_balanced_weights(
                        features.uv[accepted], weights, (camera.cx, camera.cy),
                        0.5 * min(camera.width, camera.height), rings=opts.observation_rings,
                        sectors=opts.observation_sectors)
                baseline = float(np.median(result.baseline_m[accepted]))
                # the pose errors every track of the window shares: not divided
                # by the view count, since consecutive windows share their views;
                # nor independent from frame to frame (the same keyframes): their
                # variance counts shared_error_frames times (an effective sample size)
                shared = (opts.pose_noise_m * np.sqrt(opts.shared_error_frames)
                          / max(baseline, 1e-6))
                if opts.observation_views == "all":
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", RuntimeWarning)
                        per_track = np.nanmean(log_ratio[accepted], axis=1)
                else:
                    per_track = log_ratio[accepted, -1]
                observation = observe_log_ratios(
                    per_track, weights, min_points=opts.min_observation_points,
                    floor_std=float(np.hypot(opts.observation_floor, shared)),
                )
                if observation is not None and opts.scale_observation == "reprojection":
                    fit_views, fit_use = views, accepted
                    if opts.reprojection_views == "keyframes":
                        # the smoothed keyframes only, once per change of the window
                        if self.window.version == self._observed_version:
                            observation = None
                        else:
                            self._observed_version = self.window.version
                            fit_views = self.window.views(features.ids, None,
                                                          self._keyframe_pose)
                            fit_use = accepted & (fit_views.valid.sum(axis=1) >= 2)
                    if observation is not None:
                        observation = self._reprojection_observation(
                            fit_views, fit_use, features.uv, result.baseline_m, observation,
                            camera)
                if observation is not None:
                    before = self.scale_filter.estimate.value
                    novelty = 1.0
                    if opts.novelty_floor < 1.0:
                        stamps = self.window.view_stamps(current)
                        per_view = view_weights(views.valid[accepted], weights)
                        novelty = self.novelty.novelty(stamps, per_view)
                        self.novelty.use(stamps[per_view > 0.0], oldest_ns=int(stamps[0]))
                    update = self.scale_filter.update(observation, frame.stamp_ns, novelty)
                    if update.step and np.isfinite(before):
                        # an unannounced step of ρ: the kept views' samples follow it
                        self.window.scale_relative(before / self.scale_filter.estimate.value)
                    if update.accepted and self.scale_filter.estimate.usable:
                        log_s = np.log(self.scale_filter.estimate.value)
                        uv = features.uv[accepted]
                        with np.errstate(invalid="ignore", divide="ignore"):
                            residual = (np.log(result.depth_m[accepted])
                                        - np.log(relative_now[accepted]) - log_s)
                        self._shape.update(uv, residual, observation.spread, frame.stamp_ns)
            if observation is None:
                self.scale_filter.predict(frame.stamp_ns)
            if self.window.wants(T):
                self.window.add(current)
                is_keyframe = True
            timings["scale"] = 1e3 * (time.perf_counter() - t0)
        else:
            self.scale_filter.predict(frame.stamp_ns)

        estimate = self.scale_filter.estimate
        depth = None
        points = np.empty((0, 3), np.float32)
        intensity = np.empty(0, np.uint8)
        normals = np.empty((0, 3), np.float32)
        map_points = 0
        if estimate.usable:
            t0 = time.perf_counter()
            depth = np.asarray(frame.depth_relative, np.float32) * np.float32(estimate.value)
            correction = self._shape.field()
            if correction is not None:
                depth *= correction
            timings["depth"] = 1e3 * (time.perf_counter() - t0)
            if T is not None:
                t0 = time.perf_counter()
                fuse = self.voxel_map is not None and self._map_turn % opts.map_every == 0
                if fuse:  # the map keeps its frame order: the rest of a deferred frame first
                    self.fuse_deferred_map()
                (points, intensity, normals), fused = self._cloud(
                    frame, depth, T, fuse and not defer_map)
                if fuse and defer_map:
                    if len(points):  # the turn is taken; the map's cloud comes later
                        assert self._camera is not None
                        self._deferred_map = BandedCloud(
                            depth, frame.image,
                            binned_camera(self._camera, opts.map_decimation), T,
                            decimation=opts.map_decimation, min_depth_m=opts.cloud_min_depth_m,
                            max_depth_m=opts.cloud_max_depth_m,
                            white=self.tracker.white_level or 1.0, gamma=opts.tracking.gamma)
                        self._deferred_started = False
                    else:  # whether the turn is taken depends on the map's own cloud
                        fused = self._cloud(frame, depth, T, True)[1]
                timings["cloud"] = 1e3 * (time.perf_counter() - t0)
                if len(points) or (fused is not None and len(fused[0])):
                    self._map_turn += 1
                if self.voxel_map is not None and fused is not None and len(fused[0]):
                    t0 = time.perf_counter()
                    self.voxel_map.insert(*fused)
                    map_points = len(fused[0])
                    timings["map"] = 1e3 * (time.perf_counter() - t0)

        diagnostics = FlowDiagnostics(
            has_pose=T is not None,
            keyframe=is_keyframe,
            tracks=len(features.ids),
            seeded=int(features.seeded.sum()),
            lost=features.lost,
            keyframes=len(self.window),
            triangulated=n_accepted,
            observation=float(np.exp(observation.log_scale)) if observation else float("nan"),
            observation_std=observation.std if observation else float("nan"),
            observation_points=observation.count if observation else 0,
            accepted=bool(update and update.accepted),
            gated=bool(update and update.gated),
            step=bool(update and update.step),
            exposure_step=exposure_step,
            brightness_ratio=features.brightness_ratio,
            shape_correction=self._shape.active,
            cloud_points=len(points),
            map_points=map_points,
            timings_ms=timings,
        )
        return FlowOutput(frame.stamp_ns, depth, points, intensity, normals, estimate,
                          triangulated, diagnostics)

    def _reprojection_observation(
        self, views: TrackViews, accepted: np.ndarray, uv: np.ndarray, baseline_m: np.ndarray,
        triangulated: ScaleObservation, camera: CameraModel,
    ) -> ScaleObservation | None:
        """The frame's observation by the scale-only reprojection fit (``scale_observation``).

        The tracks are balanced over the field of view by their leverage (each
        zone's share of the Gauss–Newton Hessian alike, as the triangulation
        route balances its parallax weights); the fit starts from the
        triangulated location. Its standard error is combined with the floor
        and the pose error the frame's tracks share, at the leverage-weighted
        median baseline.
        """
        opts = self.options
        start = triangulated.log_scale
        weights = np.ones(len(accepted))
        if opts.observation_rings > 1 or opts.observation_sectors > 1:
            leverage = track_leverage(views, accepted, start,
                                      reference=opts.reprojection_reference)
            chosen = accepted & (leverage > 0.0)
            balanced = area_balanced_weights(
                uv[chosen], leverage[chosen], (camera.cx, camera.cy),
                0.5 * min(camera.width, camera.height), rings=opts.observation_rings,
                sectors=opts.observation_sectors)
            weights = np.zeros(len(accepted))
            weights[chosen] = balanced / leverage[chosen]
        fit = fit_log_scale(views, accepted, weights, start,
                            reference=opts.reprojection_reference)
        if fit is None or fit.tracks < opts.min_observation_points:
            return None
        order = np.argsort(baseline_m)
        share = np.cumsum(fit.leverage[order])
        baseline = float(baseline_m[order][np.searchsorted(share, 0.5 * share[-1])])
        shared = opts.pose_noise_m * np.sqrt(opts.shared_error_frames) / max(baseline, 1e-6)
        std = float(np.sqrt(fit.std**2 + opts.observation_floor**2 + shared**2))
        return ScaleObservation(fit.log_scale, std, triangulated.spread, fit.tracks,
                                triangulated.inliers)

    def fuse_deferred_map(self, *, parts: int = 1) -> int:
        """Fuse (part of) the frame ``process(defer_map=True)`` left for the map.

        The map's cloud (``map_decimation``) of that frame's metric depth and
        pose, inserted into the voxel map in row-major bands: each call takes
        the next 1/``parts`` of its grid rows (rounded up), so ``parts``
        calls fuse it whole, with the map one call with ``parts=1`` gives
        (the bands continue one insert: :meth:`VoxelMap.insert`). The live
        node calls it after publishing each frame with ``parts=map_every``:
        the frame is fused by the time the map takes the next one.

        Returns:
            The points inserted by this call; 0 when no frame waits.
        """
        if parts < 1:
            raise ValueError(f"parts must be >= 1, got {parts}")
        pending = self._deferred_map
        if pending is None or self.voxel_map is None:
            self._deferred_map = None
            return 0
        try:
            band = pending.take(-(-pending.rows // parts))
        except Exception:
            self._deferred_map = None  # one failed frame, not every later map frame
            raise
        if len(band[0]):
            self.voxel_map.insert(*band, continues=self._deferred_started)
            self._deferred_started = True
        if pending.done:
            self._deferred_map = None
        return len(band[0])

    def _cloud(
        self, frame: FlowFrame, depth: np.ndarray, T: np.ndarray, fuse: bool
    ) -> tuple[Cloud, Cloud | None]:
        """The output's cloud and, with ``fuse``, the map's, from one back-projection.

        Each is (world points, grey level, world normals)
        (:func:`endo_flow.cloud.world_clouds`).
        """
        opts = self.options
        assert self._camera is not None
        decimations = ((opts.cloud_decimation, opts.map_decimation) if fuse
                       else (opts.cloud_decimation,))
        step = math.gcd(*decimations)
        clouds = world_clouds(depth, frame.image, binned_camera(self._camera, step), T,
                              decimations=decimations,
                              min_depth_m=opts.cloud_min_depth_m,
                              max_depth_m=opts.cloud_max_depth_m,
                              white=self.tracker.white_level or 1.0, gamma=opts.tracking.gamma)
        return clouds[0], clouds[1] if fuse else None


__all__ = [
    "FlowDiagnostics",
    "FlowFrame",
    "FlowOptions",
    "FlowOutput",
    "FlowPipeline",
    "ScaleEstimate",
    "ScaleState",
]
