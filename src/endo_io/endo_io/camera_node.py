"""``endo-camera``: a minimal camera driver for users without a ROS camera driver.

A V4L2 device (``/dev/video0`` or ``0``) or a video file, read through OpenCV
(:mod:`endo_io.video_source`), published as a driver does:

* ``/endoscope/image_raw`` (``rgb8``, ``mono8`` or ``bgr8``) and
  ``/endoscope/camera_info`` from a camera_calibration YAML (``--camera-info``;
  what ``cameracalibrator`` or ``endo-sim`` write), the same stamp and
  ``frame_id`` (``endoscope_optical_frame`` by default) on both;
* stamped at capture with the node's clock, at the source's rate: a device
  as fast as it delivers, a file at its frame rate (``--fps`` overrides;
  ``--loop`` plays it again from the start);
* with the sensor-data QoS (best effort, keep last 5) that camera drivers
  use: a frame that comes late is worth nothing, and every endo3d node and
  ``endo-record`` match it (``qos_overrides./endoscope/image_raw.publisher.reliability``
  makes it reliable).

A missing device, an unreadable file or a calibration of another size than
the frames gives one line naming the cause and exit code 2. Remap the topics
with ``--ros-args -r /endoscope/image_raw:=...`` as for any node.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from endo_io import topics
from endo_io.camera import CameraModel
from endo_io.cli import exit_on_error
from endo_io.errors import Endo3dError
from endo_io.image import array_to_image
from endo_io.process import run_node, split_ros_args
from endo_io.qos import SENSOR_DATA_QOS, publisher_overrides
from endo_io.video_source import ENCODINGS, VideoSource, VideoSourceError

PROGRAM = "endo-camera"
#: Frame rate of a file that does not say its own.
DEFAULT_FPS = 30.0


def build_parser() -> argparse.ArgumentParser:
    """The ``endo-camera`` argument parser."""
    parser = argparse.ArgumentParser(
        prog=PROGRAM,
        description="Publish a V4L2 camera or a video file as image_raw + camera_info.",
    )
    parser.add_argument("source", help="/dev/videoN, N, or a video file")
    parser.add_argument("--camera-info", type=Path, metavar="YAML",
                        help="camera_calibration YAML of this camera (without it no "
                        "camera_info is published, and SFS and flow wait for one)")
    parser.add_argument("--frame-id", default=topics.OPTICAL_FRAME,
                        help=f"header.frame_id of both topics ({topics.OPTICAL_FRAME})")
    parser.add_argument("--encoding", choices=tuple(ENCODINGS), default="rgb8",
                        help="published encoding (rgb8); mono8 for a mono calibration")
    parser.add_argument("--fps", type=float, default=None,
                        help="file: publishing rate in Hz (default: the file's, else 30)")
    parser.add_argument("--loop", action="store_true", help="file: play again from the start")
    parser.add_argument("--wait-for-subscribers", type=int, default=0, metavar="N",
                        help="before the first frame, wait until image_raw has N subscribers, at "
                        "most --wait-timeout (default 0: no wait)")
    parser.add_argument("--wait-timeout", type=float, default=30.0, metavar="SECONDS",
                        help="give up waiting for subscribers after this long (default 30)")
    return parser  # fmt: skip


class CameraNode(Node):
    """Publishes the frames of a :class:`VideoSource` from a capture thread."""

    def __init__(
        self, source: VideoSource, model: CameraModel | None, options: argparse.Namespace
    ) -> None:
        super().__init__("camera")
        self.exit_code = 0
        self.published = 0
        self._source = source
        self._model = model
        self._options = options
        self._image_pub = self.create_publisher(
            Image, topics.IMAGE_RAW, SENSOR_DATA_QOS, qos_overriding_options=publisher_overrides()
        )
        self._info_pub = self.create_publisher(
            CameraInfo, topics.CAMERA_INFO, SENSOR_DATA_QOS,
            qos_overriding_options=publisher_overrides(),
        )  # fmt: skip
        info = source.info
        fps = options.fps or info.fps or DEFAULT_FPS
        self._period_s = 1.0 / fps if info.is_file else 0.0
        rate = f"{fps:g} Hz" if info.is_file else "the device's rate"
        self.get_logger().info(
            f"{info.name}: {info.width}x{info.height} {options.encoding} at {rate} -> "
            f"{self._image_pub.topic_name}"
            + (f" + {self._info_pub.topic_name}" if model else " (no --camera-info: "
               "no camera_info)")
        )
        self._stop = threading.Event()
        self.context.on_shutdown(self._stop.set)
        self._thread = threading.Thread(target=self._capture, name="endo_camera", daemon=True)
        self._start_timer = self.create_timer(0.0, self._start)

    def _start(self) -> None:
        self._start_timer.cancel()
        if self._thread.ident is None:
            self._thread.start()

    def _wait_for_subscribers(self) -> None:
        wanted = self._options.wait_for_subscribers
        deadline = time.monotonic() + self._options.wait_timeout
        while wanted > 0 and self._image_pub.get_subscription_count() < wanted:
            if time.monotonic() > deadline:
                self.get_logger().warning(
                    f"publishing although {self._image_pub.topic_name} has fewer than "
                    f"{wanted} subscriber(s) after {self._options.wait_timeout:g} s"
                )
                return
            if self._stop.wait(0.01):
                return
        if wanted > 0:
            self._stop.wait(0.5)  # let the subscribers' side of discovery finish too

    def _capture(self) -> None:
        try:
            self._wait_for_subscribers()
            due = time.monotonic()
            while not self._stop.is_set():
                frame = self._source.read()
                if frame is None:
                    if self._options.loop and self._source.rewind():
                        frame = self._source.read()
                    if frame is None:
                        break
                if self._period_s > 0.0:
                    if self._stop.wait(max(0.0, due - time.monotonic())):
                        break
                    # A file keeps its rate; after a stall it goes on from now, not in a burst.
                    due = max(due + self._period_s, time.monotonic())
                self._publish(frame)
            if not self._stop.is_set() and not self._source.info.is_file:
                self.get_logger().error(f"{self._source.info.name} stopped delivering frames")
                self.exit_code = 1
        except Exception as error:  # a publisher used while SIGINT shuts down raises
            if not self._stop.is_set() and self.context.ok():
                self.get_logger().error(f"{type(error).__name__}: {error}")
                self.exit_code = 1
        finally:
            self.context.try_shutdown()

    def _publish(self, frame: object) -> None:
        stamp_ns = self.get_clock().now().nanoseconds
        image = array_to_image(
            frame, self._options.encoding, stamp_ns=stamp_ns, frame_id=self._options.frame_id  # type: ignore[arg-type]
        )
        self._image_pub.publish(image)
        if self._model is not None:
            self._info_pub.publish(self._model.to_camera_info(stamp_ns))
        self.published += 1

    def close(self) -> None:
        """Stop capturing and release the source."""
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join()
        self._source.close()
        print(f"{PROGRAM}: published {self.published} frames from {self._source.info.name}",
              flush=True)  # fmt: skip


def open_camera(options: argparse.Namespace) -> tuple[VideoSource, CameraModel | None]:
    """The source and its calibration, checked against each other.

    Raises:
        VideoSourceError: the source cannot be opened, or the calibration is
            of another frame size.
        CameraModelError: the calibration file does not load.
    """
    if options.fps is not None and not options.fps > 0:
        raise VideoSourceError(f"--fps must be > 0, got {options.fps}")
    model = None
    if options.camera_info is not None:
        if not options.camera_info.is_file():
            raise VideoSourceError(f"no camera calibration file {options.camera_info}")
        model = CameraModel.load_yaml(options.camera_info, frame_id=options.frame_id)
    source = VideoSource(options.source, encoding=options.encoding)
    if model is not None and (model.width, model.height) != (source.info.width,
                                                              source.info.height):  # fmt: skip
        source.close()
        raise VideoSourceError(
            f"{options.camera_info} is for {model.width}x{model.height} frames, "
            f"{source.info.name} gives {source.info.width}x{source.info.height}"
        )
    return source, model


@exit_on_error(PROGRAM, errors=(Endo3dError,))
def main(argv: Sequence[str] | None = None) -> int:
    """Run ``endo-camera``; the exit status (2: no device, unreadable file or calibration)."""
    ours, ros_args = split_ros_args(list(sys.argv if argv is None else argv))
    options = build_parser().parse_args(ours)
    source, model = open_camera(options)
    return run_node(lambda: CameraNode(source, model, options), ros_args)


if __name__ == "__main__":
    sys.exit(main())
