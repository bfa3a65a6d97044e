"""Benchmark: PhotometricCalibration.correct per frame (endo_calib).

Times the correction of a 640x480 mono8 frame and a 1920x1080 rgb8 frame
(LUT lookup + multiplication by the precomputed 1/L), with and without a
preallocated output array, and a 640x480 12-bit mono16 frame. Prints a
Markdown table for docs/benchmarks.md. Run: .venv/bin/python bench/bench_calib.py
"""

from __future__ import annotations

import time

import numpy as np
from machine import cpu_model

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


if __name__ == "__main__":
    main()
