"""Phantom acceptance of shape from shading: endo_sim bag → endo_calib → endo_sfs.

The committed colon phantom (bags/phantom_colon.mcap, 640×480 mono8, wet
mucosa with white specular highlights, Oren–Nayar σ = 0.3) is corrected with
a calibration that ``endo-calibrate`` fits from the committed gray-card bag,
then every frame with ground-truth depth is solved near-light at full
resolution with highlight masking. Issue 5 asks for a median-scaled AbsRel of
at most 0.08 against the ground truth. Masked pixels (highlights, saturated,
outside the field of view) come out NaN and are not counted; the test also
bounds how many that are.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from sensor_msgs.msg import CameraInfo

from endo_calib.calibration import PhotometricCalibration
from endo_calib.cli import build_parser, run
from endo_calib.raw_image import to_raw_frame
from endo_io.bag import BagReader, deserialize
from endo_io.camera import CameraModel
from endo_io.image import image_to_array
from endo_io.stamp import stamp_to_ns
from endo_sfs.evaluation import depth_error
from endo_sfs.options import SfsOptions
from endo_sfs.relative_depth import solve

BAGS = Path(__file__).resolve().parents[1] / "bags"
PHANTOM = BAGS / "phantom_colon.mcap"
GRAYCARD = BAGS / "graycard.mcap"
TARGET_ABS_REL = 0.08


def _ground_truth_frames() -> list[tuple[np.ndarray, np.ndarray, CameraInfo]]:
    """(raw image, true depth, camera_info) of every frame with ground-truth depth."""
    topics = ("/endoscope/image_raw", "/endoscope/camera_info", "/ground_truth/depth")
    by_topic: dict[str, dict[int, Any]] = {topic: {} for topic in topics}
    with BagReader(PHANTOM) as reader:
        for message in reader.messages(list(topics)):
            msg = deserialize(message)
            by_topic[message.topic][stamp_to_ns(msg.header.stamp)] = msg
    images, infos, depths = (by_topic[topic] for topic in topics)
    stamps = sorted(set(images) & set(infos) & set(depths))
    return [
        (
            to_raw_frame(image_to_array(images[s]), images[s].encoding),
            image_to_array(depths[s]),
            infos[s],
        )
        for s in stamps
    ]


@pytest.fixture(scope="module")
def calibration(tmp_path_factory: pytest.TempPathFactory) -> PhotometricCalibration:
    truth = yaml.safe_load((BAGS / "graycard.ground_truth.yaml").read_text())
    distance = float(truth["scene"]["gray_card"]["distance_m"])
    output = tmp_path_factory.mktemp("calib") / "photometric.yaml"
    args = build_parser().parse_args([
        "--bag", str(GRAYCARD), "--card-distance", str(distance),
        "--camera-info", str(BAGS / "graycard.camera.yaml"), "-o", str(output),
    ])
    return run(args)


def test_phantom_median_scaled_abs_rel_meets_the_target(
    calibration: PhotometricCalibration,
) -> None:
    frames = _ground_truth_frames()
    assert len(frames) == 3
    fov_radius = float(
        yaml.safe_load((BAGS / "phantom_colon.ground_truth.yaml").read_text())["camera"][
            "fov_radius_px"
        ]
    )
    errors = []
    options = SfsOptions(roughness=0.3, mask_highlights=True)
    for raw, truth, info in frames:
        camera = CameraModel.from_camera_info(info)
        irradiance = calibration.luminance(calibration.correct(raw))
        mask = camera.fov_mask(fov_radius)
        depth = solve(irradiance, camera, options, mask=mask).depth
        error = depth_error(depth, truth, scaling="median")
        # Highlights and saturated pixels are a few per cent of the view.
        assert error.coverage > 0.8
        errors.append(error.abs_rel)
    print("median-scaled AbsRel per ground-truth frame:", [round(e, 4) for e in errors])
    assert np.mean(errors) <= TARGET_ABS_REL
    assert max(errors) <= TARGET_ABS_REL + 0.005
