"""endo_io.camera.CameraInfoCache: one model per camera, rebuilt only for another camera.

Also from the CDR bytes (``camera_info_from_cdr``): the models of rclpy's messages.
"""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo

from endo_io.camera import CameraInfoCache, CameraInfoView, CameraModel, camera_info_from_cdr
from endo_io.errors import CameraModelError, UndecodableMessageError

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


def test_camera_infos_read_from_cdr_give_the_models_of_rclpy_s_messages():
    cache, reference = CameraInfoCache(), CameraInfoCache()
    distorted = CameraModel(640, 480, np.array([[500.0, 0, 319.5], [0, 501.0, 239.5], [0, 0, 1]]),
                            np.array([-0.3, 0.1, 1e-3, -2e-3, 0.01]), "plumb_bob")
    sequence = [_info(), _info(stamp_ns=2_000_000_000), _info(distorted, 3_000_000_000),
                _info(distorted, 4_000_000_000, frame_id="other"), _info(stamp_ns=5)]
    changes = []
    models = []
    for info in sequence:
        data = serialize_message(info)
        view = camera_info_from_cdr(data)
        assert isinstance(view, CameraInfoView)
        assert view.header == deserialize_message(data, CameraInfo).header
        model, changed = cache.model_of(view)
        want, want_changed = reference.model_of(deserialize_message(data, CameraInfo))
        assert model == want and model.frame_id == want.frame_id and changed == want_changed
        changes.append(changed)
        models.append(model)
    assert changes == [True, False, True, True, True]
    assert models[1] is models[0]  # only the stamp differs: the cached model, not rebuilt


def test_camera_info_bytes_that_do_not_decode_are_refused_in_one_line():
    data = serialize_message(_info())
    with pytest.raises(UndecodableMessageError, match=r"truncated at header\.frame_id"):
        camera_info_from_cdr(data[:14])
    view = camera_info_from_cdr(data[:60])  # the header is there, the camera is cut short
    with pytest.raises(UndecodableMessageError) as refused:
        CameraInfoCache().model_of(view)
    assert "\n" not in str(refused.value)
