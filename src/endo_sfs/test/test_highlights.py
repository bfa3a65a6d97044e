"""Highlight detection on synthetic shading with known specular lobes."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from endo_sfs import SfsOptions, reconstruct
from endo_sfs.errors import InvalidOptionError, SfsInputError
from endo_sfs.evaluation import depth_error
from endo_sfs.highlights import block_means, detect_highlights
from endo_sfs.synthetic import (
    SCENE_NAMES,
    Plane,
    near_light_surface,
    render_near_light,
    scene_camera,
)

SIZE = 240


def _wall(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A textured, smoothly shaded wall with two white highlights.

    Returns (irradiance with saturated pixels NaN, specular / diffuse ratio,
    field-of-view mask), all (SIZE, SIZE).
    """
    v, u = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    x, y = (u - SIZE / 2) / SIZE, (v - SIZE / 2) / SIZE
    fov = x * x + y * y < 0.48**2
    shading = 0.2 * np.exp(-3.0 * (x + 0.1) ** 2 - 2.0 * y**2)
    # Texture: ±15 % mottling and dark vessel-like lines.
    albedo = 0.4 * np.exp(0.15 * rng.standard_normal((SIZE, SIZE)))
    albedo *= 1.0 - 0.25 * (np.abs(np.sin(40.0 * x + 9.0 * y**2)) < 0.08)
    diffuse = albedo * shading
    # Two lobes: an elongated one that saturates and a weak round one that does not.
    lobe = 0.4 * np.exp(-(((x - 0.18) / 0.03) ** 2) - ((y + 0.1) / 0.12) ** 2)
    lobe += 0.2 * np.exp(-((x + 0.2) ** 2 + (y - 0.2) ** 2) / 0.035**2)
    image = diffuse + lobe
    image = np.where(image >= 0.25, np.nan, image)
    return np.where(fov, image, np.nan), lobe / diffuse, fov


def test_saturated_cores_and_shoulders_are_found_without_false_alarms():
    image, ratio, fov = _wall(np.random.default_rng(3))
    found = detect_highlights(image, fov)
    assert not found[~fov].any()
    assert np.all(found[fov & np.isnan(image)])  # every saturated pixel
    strong = fov & (ratio > 1.0)  # the lobe outshines the diffuse light
    shoulder = fov & (ratio > 0.5)  # still 40 % of the light
    faint = fov & (ratio > 0.2)  # at the texture's contrast
    assert found[strong].mean() > 0.99
    assert found[shoulder].mean() > 0.9
    assert found[faint].mean() > 0.6
    clean = fov & (ratio < 0.01)
    assert found[clean].mean() < 0.01


def test_a_broad_lobes_shoulders_are_taken_by_the_growth_and_sfs_recovers():
    # A wall facing the scope, mottled ±5 %, with the wet-tissue lobe 5·c^120
    # over Oren–Nayar (q₀ = 5, as on the simulator's tissue). The lobe is
    # about as wide as the baseline's opening, so the baseline rises under
    # it and the excess test alone stops where the lobe is still ~ the
    # diffuse light; the growth takes the shoulders (measured: 58 % → 100 %
    # of the pixels where the lobe is > 20 % of the diffuse light; AbsRel
    # 0.053 → 0.008).
    camera = scene_camera(SIZE)
    wall = Plane((0.0, 0.0, 2.0), (0.1, -0.05, -1.0))
    diffuse = render_near_light(camera, wall, 0.3).irradiance
    glossy = render_near_light(camera, wall, 0.3, 5.0, 120.0)
    v, u = np.mgrid[0:SIZE, 0:SIZE] / SIZE
    albedo = np.exp(0.05 * np.sin(9.0 * u + 2.0) * np.cos(7.0 * v)
                    + 0.03 * np.random.default_rng(1).standard_normal((SIZE, SIZE)))
    image = diffuse * albedo + (glossy.irradiance - diffuse)
    ratio = (glossy.irradiance - diffuse) / (diffuse * albedo)
    fov = camera.fov_mask(0.48 * SIZE) & np.isfinite(image)
    errors = {}
    for growth in (1.0, 2.0):
        found = detect_highlights(image, fov, shoulder_growth=growth)
        assert found[fov & (ratio > 0.5)].mean() > (0.75 if growth == 1.0 else 0.99)
        depth = reconstruct(image, camera, SfsOptions(roughness=0.3), mask=fov & ~found)
        errors[growth] = depth_error(depth, glossy.depth, fov)
        shoulder = found[fov & (ratio > 0.2)].mean()
        assert shoulder < 0.7 if growth == 1.0 else shoulder > 0.99
    assert errors[1.0].abs_rel > 0.04
    assert errors[2.0].abs_rel < 0.012 and errors[2.0].coverage > 0.65
    # the default grows
    np.testing.assert_array_equal(detect_highlights(image, fov), found)


def test_a_highlight_is_found_at_any_brightness_scale():
    image, _, fov = _wall(np.random.default_rng(4))
    found = detect_highlights(image, fov)
    np.testing.assert_array_equal(detect_highlights(37.0 * image, fov), found)


def test_without_a_mask_only_enclosed_nan_holes_count_as_saturated():
    image, ratio, fov = _wall(np.random.default_rng(5))
    found = detect_highlights(image)
    assert not found[~fov].any()  # the unseen corners are not highlights
    assert found[fov & (ratio > 1.0)].mean() > 0.99


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_pure_diffuse_shading_has_no_highlight(name):
    camera = scene_camera(256)
    image = render_near_light(camera, near_light_surface(name), 0.3).irradiance
    mask = camera.fov_mask(0.48 * 256) & np.isfinite(image)
    assert not detect_highlights(image, mask).any()


def test_saturation_level_marks_saturated_pixels():
    image, _, fov = _wall(np.random.default_rng(6))
    clipped = np.where(np.isnan(image) & fov, 0.25, image)
    found = detect_highlights(clipped, fov, saturation=0.25)
    assert np.all(found[clipped >= 0.25])


def test_an_empty_frame_has_no_highlight():
    assert not detect_highlights(np.zeros((SIZE, SIZE))).any()
    assert not detect_highlights(np.full((SIZE, SIZE), np.nan)).any()


def test_bad_arguments_raise_named_errors():
    image, _, fov = _wall(np.random.default_rng(7))
    with pytest.raises(SfsInputError):
        detect_highlights(image[..., None], fov)
    with pytest.raises(SfsInputError):
        detect_highlights(image, fov[:10])
    with pytest.raises(SfsInputError):
        detect_highlights(image, fov, core_excess=0.2, shoulder_excess=0.5)
    with pytest.raises(SfsInputError):
        detect_highlights(image, fov, opening_radius=0.0)
    with pytest.raises(SfsInputError):
        detect_highlights(image, fov, downsample=0)
    with pytest.raises(SfsInputError):
        detect_highlights(image, fov, shoulder_growth=0.5)
    with pytest.raises(SfsInputError):
        detect_highlights(image, fov, threads=0)


@pytest.mark.parametrize("downsample", [1, 2])
@pytest.mark.parametrize("use_mask", [True, False])
def test_two_threads_find_the_same_pixels_as_one(downsample, use_mask):
    # The two threads compute the baseline's two independent halves (and every
    # numba kernel runs on one thread): the same values, so the same mask.
    image, ratio, fov = _wall(np.random.default_rng(5))
    mask = fov if use_mask else None
    one = detect_highlights(image, mask, downsample=downsample)
    assert one[fov & np.isnan(image)].all() and one[fov & (ratio > 1.0)].mean() > 0.99
    for _ in range(3):  # the second thread's state does not carry over
        np.testing.assert_array_equal(
            detect_highlights(image, mask, downsample=downsample, threads=2), one)


@pytest.mark.parametrize("use_mask", [True, False])
def test_detection_on_the_halved_image_finds_the_same_lobes(use_mask):
    image, ratio, fov = _wall(np.random.default_rng(3))
    full = detect_highlights(image, fov if use_mask else None)
    half = detect_highlights(image, fov if use_mask else None, downsample=2)
    assert half.shape == image.shape and not half[~fov].any()
    assert np.all(half[fov & np.isnan(image)])  # every saturated pixel
    assert half[fov & (ratio > 1.0)].mean() > 0.99
    assert half[fov & (ratio > 0.5)].mean() > 0.9
    assert half[fov & (ratio < 0.01)].mean() < 0.01
    # The two masks differ only along the lobes' edges (blocks of 2 × 2 pixels).
    assert np.mean(half != full) < 0.01


def test_block_means_average_the_data_and_keep_saturation():
    image = np.array([[1.0, 3.0, 5.0], [np.nan, 7.0, 0.0], [2.0, 8.0, 11.0]])
    region = np.array([[True, True, True], [True, True, True], [True, True, False]])
    small, inside = block_means(image, region, 10.0, 2)
    # Block (0, 0) holds a NaN (saturated); (0, 1) averages 5 (0 is dark, not data);
    # (1, 0) is the geometric mean of 2 and 8 (the detection works on ln I);
    # (1, 1) is out of the region (its one pixel, saturated, is not in it).
    assert np.isnan(small[0, 0])
    assert small[0, 1] == pytest.approx(5.0, rel=1e-6)
    assert small[1, 0] == pytest.approx(4.0, rel=1e-6)
    np.testing.assert_array_equal(inside, [[True, True], [True, False]])
    small, _ = block_means(np.full((2, 2), 9.0), np.ones((2, 2), bool), 8.0, 2)
    assert np.isnan(small[0, 0])  # at or above the saturation level


def test_holes_are_filled_as_scipy_fills_them():
    from scipy import ndimage

    from endo_sfs.highlights import filled

    rng = np.random.default_rng(11)
    for _ in range(50):
        height, width = rng.integers(1, 40, 2)
        inside = rng.random((height, width)) < rng.random()
        np.testing.assert_array_equal(filled(inside), ndimage.binary_fill_holes(inside))


@pytest.mark.parametrize("radius", [8, 18])
def test_disc_minimum_equals_opencvs_erosion(radius):
    import cv2

    from endo_sfs.highlights import _disc, _disc_half_widths, _disc_minimum

    rng = np.random.default_rng(radius)
    for shape in ((120, 160), (7, 30), (45, 3)):
        values = rng.standard_normal(shape).astype(np.float32)
        values[rng.random(shape) < 0.2] = 1e30  # cells that take no part
        widths = _disc_half_widths(radius)
        np.testing.assert_array_equal(_disc_minimum(values, widths),
                                      cv2.erode(values, _disc(radius)))


def test_detection_follows_the_solve_grid_and_image_size_unless_set():
    assert SfsOptions().detection_downsample(240) == 1
    assert SfsOptions().detection_downsample(479) == 1
    assert SfsOptions().detection_downsample(480) == 2
    assert SfsOptions(solve_scale=0.5).detection_downsample(240) == 2
    assert SfsOptions(solve_scale=0.25).detection_downsample(480) == 2
    assert SfsOptions(solve_scale=0.5, highlight_downsample=1).detection_downsample(480) == 1
    assert SfsOptions(highlight_downsample=3).detection_downsample(240) == 3
    with pytest.raises(InvalidOptionError, match="highlight_downsample"):
        SfsOptions(highlight_downsample=-1)


def test_halved_blocks_equal_block_means():
    from endo_sfs.highlights import _halved

    rng = np.random.default_rng(5)
    image = np.exp(rng.normal(0.0, 2.0, (40, 60))).astype(np.float32)
    image[rng.random(image.shape) < 0.05] = np.nan
    image[rng.random(image.shape) < 0.05] = 0.0
    image[rng.random(image.shape) < 0.05] = 50.0
    region = rng.random(image.shape) < 0.8
    small, inside = _halved(image, region, 40.0)
    expected, expected_inside = block_means(image, region, 40.0, 2)
    np.testing.assert_array_equal(inside, expected_inside)
    np.testing.assert_allclose(small, expected, rtol=1e-6)  # NaN where saturated in both


def test_two_threads_on_numbas_workqueue_layer_run_in_turn_and_find_the_same_pixels():
    # numba's workqueue layer aborts the process when two threads launch parallel kernels
    # at once (no libgomp or TBB on the machine, or NUMBA_THREADING_LAYER=workqueue); the
    # detection's second thread then runs its part on the calling thread.
    script = (
        "import numpy as np\n"
        "from endo_sfs.highlights import detect_highlights\n"
        "import threading\n"
        "from endo_sfs.second_thread import beside, threading_layer_is_threadsafe\n"
        "same = beside(threading.get_ident).result() == threading.get_ident()\n"
        "rng = np.random.default_rng(5)\n"
        "image = (0.2 + 0.05 * rng.random((240, 320))).astype(np.float32)\n"
        "image[100:110, 150:165] = 3.0\n"
        "one = detect_highlights(image, None)\n"
        "for _ in range(10):\n"
        "    assert np.array_equal(detect_highlights(image, None, threads=2), one)\n"
        "print(threading_layer_is_threadsafe(), same, int(one.sum()))\n"
    )
    env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue"}
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    threadsafe, on_the_calling_thread, found = result.stdout.split()
    assert threadsafe == "False" and on_the_calling_thread == "True" and int(found) > 100
