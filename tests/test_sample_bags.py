"""The committed sample recordings: size budget, and calibration against their ground truth."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from endo_calib.calibration import PhotometricCalibration
from endo_io.bag import BagReader

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT / "bags"


def test_sample_bags_fit_the_25_mb_budget_and_list_their_topics():
    files = [p for p in BAGS.iterdir() if p.is_file() and not p.is_symlink()]
    assert sum(p.stat().st_size for p in files) <= 25 * 1024 * 1024
    expected = {
        "phantom_colon.mcap": {"/endoscope/image_raw", "/endoscope/camera_info", "/tracker/pose",
                               "/ground_truth/depth", "/ground_truth/camera_pose"},
        "graycard.mcap": {"/endoscope/image_raw", "/calibration/gray_level"},
        "handeye.mcap": {"/endoscope/image_raw", "/tracker/pose"},
    }
    for name, topics in expected.items():
        with BagReader(BAGS / name) as reader:
            assert topics <= set(reader.topics), name


def test_endo_calibrate_on_the_gray_card_bag_recovers_the_true_photometry(tmp_path):
    output = tmp_path / "photometric.yaml"
    subprocess.run(
        [str(Path(sys.executable).parent / "endo-calibrate"), "--bag", str(BAGS / "graycard.mcap"),
         "-o", str(output)],
        check=True, capture_output=True, text=True, timeout=120,
    )
    calibration = PhotometricCalibration.load(output)
    true_inverse = np.load(BAGS / "graycard.inverse_response.npy")
    values = np.arange(5, 251)
    inverse = np.asarray(calibration.inverse_response, dtype=np.float64).reshape(256, -1)[:, 0]
    assert np.max(np.abs(inverse[values] - true_inverse[values])) <= 0.01
    true_light = np.load(BAGS / "graycard.light_map.npy")
    light = np.asarray(calibration.light_map, dtype=np.float64)
    light = light[..., 0] if light.ndim == 3 else light
    used = calibration.fov_mask & (true_light > 0)
    assert used.mean() > 0.5
    rms = np.sqrt(np.mean((light[used] / true_light[used] - 1.0) ** 2))
    assert rms <= 0.01
