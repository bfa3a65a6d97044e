"""Benchmark: PhotometricCalibration.correct per frame, and the gray-card fit's accuracy.

1. Times the correction of a 640x480 mono8 frame and a 1920x1080 rgb8 frame
   (LUT lookup + multiplication by the precomputed 1/L), with and without a
   preallocated output array, and a 640x480 12-bit mono16 frame. Prints a
   Markdown table for docs/benchmarks.md.
2. ``--accuracy``: the inverse response's error against the truth where the
   top of the curve is extrapolated: endo_sim renders (160x120, 4 frames per
   card, 7 cards) whose 0.8 card peaks 5, 10 or 20 codes below full scale,
   gamma and S-curve, on two seeds the fit was not tuned on (2027 is the
   test's, 4242), plus a logistic response outside the tail's family
   (rendered through the same model, the honest limit), and
   ``endo-calibrate`` on bags/graycard.mcap. Writes the section
   "endo_calib gray-card accuracy" of docs/benchmarks.md.

Run: .venv/bin/python bench/bench_calib.py [--accuracy]
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
from machine import cpu_model
from results import replace_section

from endo_calib.calibration import PhotometricCalibration
from endo_calib.synthetic import synthetic_calibration


def calibration(width: int, height: int, bits: int, colour: bool) -> PhotometricCalibration:
    return synthetic_calibration(
        width,
        height,
        bits=bits,
        colour=colour,
        fov_radius2=1.2,
        light_model_degree=8,
        light_source="model",
    )


def time_ms(fn, repeats: int = 200) -> tuple[float, float]:
    for _ in range(5):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(samples)), float(np.percentile(samples, 90))


def main() -> None:
    rng = np.random.default_rng(0)
    cases = [
        ("640x480 mono8", 640, 480, 8, False, 300),
        ("1920x1080 rgb8", 1920, 1080, 8, True, 100),
        ("640x480 mono16 (12-bit)", 640, 480, 12, False, 200),
    ]
    rows = []
    for name, w, h, bits, colour, repeats in cases:
        cal = calibration(w, h, bits, colour)
        shape = (h, w, 3) if colour else (h, w)
        dtype = np.uint8 if bits == 8 else np.uint16
        raw = rng.integers(0, 1 << bits, shape).astype(dtype)
        out = np.empty(shape, np.float32)
        cal.correct(raw)  # builds the per-size tables once
        fresh = time_ms(lambda cal=cal, raw=raw: cal.correct(raw), repeats)
        reused = time_ms(lambda cal=cal, raw=raw, out=out: cal.correct(raw, out=out), repeats)
        rows.append((name, fresh, reused))
    print(f"machine: {cpu_model()}, {len(__import__('os').sched_getaffinity(0))} cores")
    print("| frame | correct(raw) median / p90 ms | correct(raw, out=buf) median / p90 ms |")
    print("|---|---|---|")
    for name, fresh, reused in rows:
        print(f"| {name} | {fresh[0]:.2f} / {fresh[1]:.2f} | {reused[0]:.2f} / {reused[1]:.2f} |")


ROOT = Path(__file__).resolve().parents[1]
ACCURACY_TITLE = "## endo_calib gray-card accuracy"


class LogisticResponse:
    """A response outside the tail's family: a logistic in E, rescaled to f(0) = 0, f(1) = 1."""

    def __init__(self, steepness: float = 7.0, middle: float = 0.45) -> None:
        self.k, self.mid = steepness, middle
        self.grid = np.linspace(0.0, 1.0, 200001)
        self.values = self(self.grid)

    def __call__(self, irradiance):
        e = np.clip(np.asarray(irradiance, dtype=np.float64), 0.0, 1.0)
        low, high = self._s(-self.k * self.mid), self._s(self.k * (1 - self.mid))
        return (self._s(self.k * (e - self.mid)) - low) / (high - low)

    @staticmethod
    def _s(z):
        return 1.0 / (1.0 + np.exp(-np.asarray(z)))

    def inverse(self, value):
        return np.interp(np.clip(np.asarray(value, dtype=np.float64), 0, 1), self.values, self.grid)

    def inverse_lut(self, bits: int):
        top = (1 << bits) - 1
        return self.inverse(np.arange(top + 1) / top)

    def code_thresholds(self, bits: int):
        top = (1 << bits) - 1
        return self.inverse((np.arange(top) + 0.5) / top)


def short_of_saturation(kind: str, short: int, seed: int) -> tuple[float, float, int, str]:
    """(max error all codes %, above the data %, observed top, top model) of one render."""
    from endo_calib import GrayLevel, PhotometricCalibration, fit_gray_card
    from endo_calib.geometry import CardPose
    from endo_io.camera import CameraModel
    from endo_sim.graycard import render_gray_card
    from endo_sim.photometry import Photometry
    from endo_sim.response import CameraResponse

    width, height = 160, 120
    camera = CameraModel.pinhole(
        width, height, 0.5 * width, 0.5 * width, 0.5 * (width - 1), 0.5 * (height - 1),
        D=np.array([-0.12, 0.02, 0.0, 0.0, 0.0]),
    )
    if kind == "gamma":
        response = CameraResponse.gamma()
    elif kind == "s_curve":
        response = CameraResponse.s_curve()
    else:
        response = LogisticResponse()
    photometry = Photometry(roughness=0.0, response=CameraResponse.gamma(), bit_depth=8)
    object.__setattr__(photometry, "response", response)  # any object with the response's methods
    distance = 0.03 * float(np.sqrt(0.8 / float(response.inverse((255 - short) / 255))))
    rng = np.random.default_rng(seed)
    pose = CardPose(distance_m=distance)
    levels = [
        GrayLevel(rho, [render_gray_card(camera, photometry, rho, distance, rng=rng,
                                         fov_radius_px=0.5 * height) for _ in range(4)], pose)
        for rho in (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
    ]
    report = fit_gray_card(levels, camera)
    calibration = PhotometricCalibration.from_fit(report)
    error = np.abs(calibration.inverse_response - response.inverse_lut(8))
    extent = report.channels["mono"].extent
    assert extent is not None
    above = float(error[extent.observed_high + 1 :].max(initial=0.0))
    model = extent.top_model.split(":")[0]
    return 100 * float(error.max()), 100 * above, extent.observed_high, model


def sample_bag() -> tuple[float, float, float]:
    """endo-calibrate on bags/graycard.mcap: (max error 5..250 %, all codes %, light RMS %)."""
    from endo_calib import PhotometricCalibration

    bag = ROOT / "bags" / "graycard.mcap"
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "photometric.yaml"
        subprocess.run(
            [str(Path(sys.executable).with_name("endo-calibrate")), "--bag", str(bag),
             "--card-distance", "0.0265", "--camera-info", str(ROOT / "bags/graycard.camera.yaml"),
             "-o", str(out)], check=True, capture_output=True,
        )
        calibration = PhotometricCalibration.load(out)
    truth = np.load(ROOT / "bags" / "graycard.inverse_response.npy")
    error = np.abs(calibration.inverse_response - truth)
    light = np.load(ROOT / "bags" / "graycard.light_map.npy")
    inside = calibration.fov_mask & (light > 0)
    relative = calibration.light_map[inside] / light[inside] - 1.0
    return (100 * float(error[5:251].max()), 100 * float(error.max()),
            100 * float(np.sqrt(np.mean(relative**2))))


def accuracy() -> None:
    load = os.getloadavg()
    lines = [
        ACCURACY_TITLE,
        "",
        f"`bench/bench_calib.py --accuracy`, {date.today().isoformat()}, {cpu_model()}, "
        f"{len(os.sched_getaffinity(0))} cores shared with other helpers' work (load average "
        f"{load[0]:.1f} at the start). Max |g − g_true| in % of full scale over every raw "
        "value 0..255, and over the extrapolated values only (above the highest one observed). "
        "endo_sim renders, 160x120, mild barrel distortion, circular field of view, shot and "
        "read noise, 7 cards 0.2–0.8, 4 frames each, the 0.8 card peaking 5/10/20 codes below "
        "full scale at the centre (no sample saturates). The fit's tail constants (window 30 % "
        "of full scale, join 60 % down it) and its starts were tuned on seeds 5, 11 and 12; "
        "seed 2027 is tests/test_response_top.py's, 4242 a second one. The logistic response "
        "is outside the tail's family (the limit of any extrapolation).",
        "",
        "| response | codes short | seed | max error, all codes | above the data | "
        "observed top | top found by |",
        "|---|---|---|---|---|---|---|",
    ]
    for kind in ("gamma", "s_curve", "logistic"):
        for short in (5, 10, 20):
            for seed in (2027, 4242) if kind != "logistic" else (2027,):
                worst, above, top, model = short_of_saturation(kind, short, seed)
                lines.append(f"| {kind} | {short} | {seed} | {worst:.2f} % | {above:.2f} % | "
                             f"{top} | {model} |")
                print(lines[-1], flush=True)
    g5, g_all, light = sample_bag()
    lines += [
        "",
        f"`endo-calibrate --bag bags/graycard.mcap` (640x480, 3 frames per card, the 0.8 card "
        f"just saturating at the centre): inverse response within {g5:.2f} % of full scale over "
        f"values 5–250 ({g_all:.2f} % over all values), light map {light:.3f} % relative RMS "
        "inside the field of view, against the files beside the bag.",
        "",
    ]
    print(lines[-2])
    replace_section("\n".join(lines), ACCURACY_TITLE)


if __name__ == "__main__":
    if "--accuracy" in sys.argv:
        accuracy()
    else:
        main()
