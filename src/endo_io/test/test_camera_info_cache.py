"""endo_io.camera.CameraInfoCache: one model per camera, rebuilt only for another camera."""

from __future__ import annotations

import numpy as np
import pytest

from endo_io.camera import CameraInfoCache, CameraModel
from endo_io.errors import CameraModelError

CAMERA = CameraModel.pinhole(320, 240, 300.0, 301.0, 159.5, 119.5)


def _info(model: CameraModel = CAMERA, stamp_ns: int = 1_000_000_000, frame_id: str = "cam"):
    info = model.to_camera_info(stamp_ns)
    info.header.frame_id = frame_id
    return info


def test_the_same_camera_gives_the_same_model_whatever_the_stamp():
    cache = CameraInfoCache()
    first, changed = cache.model_of(_info())
    assert changed and cache.model is first
    assert first.frame_id == "cam" and first.K[0, 0] == 300.0 and first.K[1, 2] == 119.5
    again, changed = cache.model_of(_info(stamp_ns=2_000_000_000))
    assert again is first and not changed


def test_another_intrinsic_or_frame_id_gives_a_new_model():
    cache = CameraInfoCache()
    first, _ = cache.model_of(_info())
    zoomed = CameraModel.pinhole(320, 240, 330.0, 331.0, 159.5, 119.5)
    second, changed = cache.model_of(_info(zoomed))
    assert changed and second is not first and second.K[0, 0] == 330.0
    # the frame_id is part of the model: one with the old frame_id is never reused
    renamed, _ = cache.model_of(_info(zoomed, frame_id="other_optical_frame"))
    assert renamed is not second and renamed.frame_id == "other_optical_frame"
    back, changed = cache.model_of(_info())
    assert changed and back.K[0, 0] == 300.0 and back.frame_id == "cam"


def test_a_camera_info_without_a_model_raises_and_keeps_the_last_model():
    cache = CameraInfoCache()
    first, _ = cache.model_of(_info())
    bad = _info()
    bad.k = list(np.zeros(9))  # no focal length
    with pytest.raises(CameraModelError):
        cache.model_of(bad)
    assert cache.model is first
    assert cache.model_of(_info())[0] is first
