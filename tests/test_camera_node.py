"""``endo-camera``: a video file through the real node to a subscriber, and its refusals.

A 64×48 MJPG file of 20 frames at 20 Hz is written here with cv2.VideoWriter,
each frame a different grey level; ``endo-camera FILE --camera-info YAML``
runs as its own process and a best-effort subscriber in this process gets
every frame: rgb8 of the file's size with the written grey levels, in order,
each with a camera_info of the same stamp and frame_id equal to the YAML's
calibration, stamps increasing and spread at least over the file's duration
(the node never publishes faster than the source's rate). Then ``--loop``
plays past the end of the file. A missing device, a missing or undecodable
file and a calibration of another size each give one line and exit code 2.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import CameraInfo, Image

from endo_io import topics
from endo_io.camera import CameraModel
from endo_io.image import image_to_array
from endo_io.qos import SENSOR_DATA_QOS
from endo_io.stamp import stamp_to_ns

CAMERA = str(Path(sys.executable).parent / "endo-camera")
WIDTH, HEIGHT, FRAMES, FPS = 64, 48, 20, 20.0


@pytest.fixture(scope="module")
def video(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, CameraModel]:
    out = tmp_path_factory.mktemp("camera")
    path = out / "scope.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (WIDTH, HEIGHT))
    assert writer.isOpened()
    for index in range(FRAMES):
        writer.write(np.full((HEIGHT, WIDTH, 3), 10 + 12 * index, np.uint8))
    writer.release()
    model = CameraModel.pinhole(WIDTH, HEIGHT, 40.0, 40.0, 31.5, 23.5)
    model.save_yaml(out / "camera.yaml")
    return path, out / "camera.yaml", CameraModel.load_yaml(out / "camera.yaml")


class Listener:
    """Images and camera_infos of /endoscope/*, in a context of their own."""

    def __init__(self) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("camera_listener", context=self.context)
        self.images: list[Image] = []
        self.infos: list[CameraInfo] = []
        self.node.create_subscription(Image, topics.IMAGE_RAW, self.images.append, SENSOR_DATA_QOS)
        self.node.create_subscription(
            CameraInfo, topics.CAMERA_INFO, self.infos.append, SENSOR_DATA_QOS
        )
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_while(self, process: subprocess.Popen[str], seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while process.poll() is None and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)
        for _ in range(20):  # what is still queued
            self.executor.spin_once(timeout_sec=0.02)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


@pytest.mark.ros
def test_a_video_file_is_published_frame_for_frame_with_camera_info(video):
    path, calibration, model = video
    listener = Listener()
    try:
        process = subprocess.Popen(
            [CAMERA, str(path), "--camera-info", str(calibration), "--wait-for-subscribers", "1"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        listener.spin_while(process, 60)
        output = process.communicate(timeout=30)[0]
    finally:
        listener.close()
    assert process.returncode == 0, output
    assert f"published {FRAMES} frames" in output
    images, infos = listener.images, listener.infos
    assert len(images) == FRAMES, output
    levels = [float(image_to_array(m).mean()) for m in images]
    assert all(m.encoding == "rgb8" and (m.width, m.height) == (WIDTH, HEIGHT) for m in images)
    assert np.allclose(levels, [10 + 12 * i for i in range(FRAMES)], atol=3.0), levels
    stamps = [stamp_to_ns(m.header.stamp) for m in images]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    assert (stamps[-1] - stamps[0]) / 1e9 >= 0.9 * (FRAMES - 1) / FPS  # the source's rate
    assert {m.header.frame_id for m in images} == {topics.OPTICAL_FRAME}
    assert [stamp_to_ns(m.header.stamp) for m in infos] == stamps
    for info in infos:
        assert info.header.frame_id == topics.OPTICAL_FRAME
        assert CameraModel.from_camera_info(info) == model


@pytest.mark.ros
def test_loop_plays_past_the_end_of_the_file(video):
    path, _, _ = video
    listener = Listener()
    try:
        process = subprocess.Popen(
            [CAMERA, str(path), "--loop", "--fps", "40", "--wait-for-subscribers", "1"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        deadline = time.monotonic() + 60
        while len(listener.images) < FRAMES + 10 and time.monotonic() < deadline:
            listener.executor.spin_once(timeout_sec=0.05)
        process.send_signal(2)
        output = process.communicate(timeout=30)[0]
    finally:
        if process.poll() is None:
            process.kill()
        listener.close()
    assert len(listener.images) >= FRAMES + 10, output
    assert process.returncode == 0, output
    levels = [round((float(image_to_array(m).mean()) - 10) / 12) for m in listener.images]
    assert 0 in levels[levels.index(FRAMES - 1):], levels  # back at the first frame


@pytest.mark.parametrize(("argv", "message"), [
    (["/dev/video57"], "no video device /dev/video57"),
    (["missing.mp4"], "no video file missing.mp4"),
    (["junk.mp4"], "cannot decode video file"),
    (["VIDEO", "--camera-info", "small.yaml"], "is for 32x24 frames"),
])  # fmt: skip
def test_what_cannot_be_read_gives_one_line_and_exit_2(video, tmp_path, argv, message):
    path, _, _ = video
    (tmp_path / "junk.mp4").write_bytes(b"not a video")
    CameraModel.pinhole(32, 24, 20.0, 20.0, 15.5, 11.5).save_yaml(tmp_path / "small.yaml")
    argv = [str(path) if a == "VIDEO" else a for a in argv]
    result = subprocess.run([CAMERA, *argv], cwd=tmp_path, capture_output=True, text=True,
                            timeout=60, check=False)  # fmt: skip
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("endo-camera: ") and message in lines[0], lines
