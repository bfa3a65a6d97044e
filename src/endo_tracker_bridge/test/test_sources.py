"""Each source's conversion, against the formats the real libraries produce."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pyigtl
import pytest
from geometry_msgs.msg import PoseStamped
from scipy.spatial.transform import Rotation
from sksurgerycore.baseclasses.tracker import SKSBaseTracker
from sksurgerynditracker.nditracker import NDITracker

from endo_io.stamp import ns_to_stamp
from endo_tracker_bridge.conventions import LengthUnit
from endo_tracker_bridge.errors import (
    IgtlMessageError,
    NdiFrameError,
    NonFinitePoseError,
    NonOrthonormalRotationError,
    NonUnitQuaternionError,
    ToolNotVisibleError,
    TrackerLogError,
    UnexpectedFrameError,
)
from endo_tracker_bridge.sample import ToolStatus
from endo_tracker_bridge.sources.csv import (
    CsvReplaySource,
    TrackerLogRowError,
    read_tracker_log,
    sample_from_log_row,
)
from endo_tracker_bridge.sources.igtl import (
    IgtlFrame,
    IgtlSource,
    parse_header,
    sample_from_igtl_frame,
)
from endo_tracker_bridge.sources.ndi import (
    NdiOptions,
    NdiSource,
    readings_from_ndi_frame,
    sample_from_ndi_reading,
)
from endo_tracker_bridge.sources.ros import sample_from_pose_stamped
from endo_tracker_bridge.validation import SampleGate

ROTATION = Rotation.from_euler("xyz", [20.0, -35.0, 110.0], degrees=True)
TRANSLATION_MM = np.array([12.5, -230.25, -1405.0])


# -- ros ----------------------------------------------------------------------------


def _pose_msg(q_xyzw, position, frame="ndi", stamp_ns=1_700_000_000_250_000_000):
    msg = PoseStamped()
    msg.header.frame_id = frame
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, position)
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = map(float, q_xyzw)
    return msg


def test_ros_pose_in_millimetres_becomes_metres():
    msg = _pose_msg(ROTATION.as_quat(), TRANSLATION_MM)
    sample = sample_from_pose_stamped(msg, LengthUnit.MILLIMETRE, expected_frame_id="ndi")
    np.testing.assert_allclose(sample.translation_m, TRANSLATION_MM / 1000.0, rtol=1e-15)
    np.testing.assert_allclose(sample.rotation, ROTATION.as_matrix(), atol=1e-12)
    assert sample.stamp_ns == 1_700_000_000_250_000_000
    metres = sample_from_pose_stamped(_pose_msg(ROTATION.as_quat(), [0.1, 0.2, 0.3]))
    np.testing.assert_allclose(metres.translation_m, [0.1, 0.2, 0.3])


def test_ros_pose_rejections():
    with pytest.raises(UnexpectedFrameError, match="'camera'"):
        sample_from_pose_stamped(
            _pose_msg([0, 0, 0, 1], [0, 0, 0], frame="camera"), expected_frame_id="ndi"
        )
    with pytest.raises(NonUnitQuaternionError):
        sample_from_pose_stamped(_pose_msg([0, 0, 0.2, 1], [0, 0, 0]))
    with pytest.raises(NonFinitePoseError):
        sample_from_pose_stamped(_pose_msg([0, 0, 0, 1], [0, np.nan, 0]))


# -- OpenIGTLink (real pyigtl messages, packed to bytes) ----------------------------


def _igtl_frame(message) -> IgtlFrame:
    raw = message.pack()
    header, stamp_ns, crc = parse_header(raw[:58])
    return IgtlFrame(header, raw[58:], stamp_ns, crc, receive_ns=123)


def test_igtl_transform_in_millimetres_with_exact_stamp():
    matrix = np.eye(4)
    matrix[:3, :3] = ROTATION.as_matrix()
    matrix[:3, 3] = TRANSLATION_MM
    message = pyigtl.TransformMessage(
        matrix, timestamp=1_700_000_123.25, device_name="ScopeToTracker"
    )
    sample = sample_from_igtl_frame(_igtl_frame(message), LengthUnit.MILLIMETRE)
    assert sample.tool_id == "ScopeToTracker"
    # float32 on the wire: 1405 mm is good to ~1e-4 mm
    np.testing.assert_allclose(sample.translation_m, TRANSLATION_MM / 1000.0, atol=1e-7)
    np.testing.assert_allclose(sample.rotation, ROTATION.as_matrix(), atol=1e-6)
    # the 2^-32 s fraction of 0.25 s is exact
    assert sample.stamp_ns == 1_700_000_123_250_000_000
    assert sample_from_igtl_frame(_igtl_frame(message), stamp_from="receive").stamp_ns == 123


def test_igtl_rejections():
    good = pyigtl.TransformMessage(np.eye(4), timestamp=10.0, device_name="Scope")
    frame = _igtl_frame(good)
    corrupt = IgtlFrame(frame.header, b"\x00" + frame.body[1:], frame.stamp_ns, frame.crc, 0)
    with pytest.raises(IgtlMessageError, match="CRC"):
        sample_from_igtl_frame(corrupt)
    with pytest.raises(IgtlMessageError, match="not TRANSFORM"):
        sample_from_igtl_frame(_igtl_frame(pyigtl.StringMessage("hi", device_name="Scope")))
    sheared = np.eye(4)
    sheared[0, 1] = 0.2
    with pytest.raises(NonOrthonormalRotationError):
        sample_from_igtl_frame(_igtl_frame(pyigtl.TransformMessage(sheared, device_name="Scope")))
    nan = np.eye(4)
    nan[1, 3] = np.nan
    with pytest.raises(NonFinitePoseError):
        sample_from_igtl_frame(_igtl_frame(pyigtl.TransformMessage(nan, device_name="Scope")))


# -- NDI: frames assembled by scikit-surgery's own tracker base class ---------------


class _LibraryFrames(SKSBaseTracker):
    """Builds get_frame() tuples with sksurgerycore's own buffering code.

    NDITracker.get_frame() hands ndicapi's (qw, qx, qy, qz, x, y, z) per tool
    to ``add_frame_to_buffer(..., rot_is_quaternion=True)`` and returns
    ``get_smooth_frame``; this does exactly that with chosen values.
    """

    def __init__(self, use_quaternions=False):
        super().__init__({"use quaternions": use_quaternions, "smoothing buffer": 1})

    def frame(self, handles, stamp_s, frame_number, quaternions_wxyz, translations_mm, qualities):
        self.add_frame_to_buffer(
            handles,
            [stamp_s] * len(handles),
            [frame_number] * len(handles),
            quaternions_wxyz,
            translations_mm,
            qualities,
            rot_is_quaternion=True,
        )
        return self.get_smooth_frame(handles)

    def close(self):
        pass

    def get_frame(self):
        raise NotImplementedError

    def get_tool_descriptions(self):
        return [], []

    def start_tracking(self):
        pass

    def stop_tracking(self):
        pass


def _ndi_quaternion():
    x, y, z, w = ROTATION.as_quat()
    return np.array([w, x, y, z])


@pytest.mark.parametrize("use_quaternions", [False, True])
def test_ndi_frame_converts_millimetres_and_w_first_quaternions(use_quaternions):
    library = _LibraryFrames(use_quaternions)
    frame = library.frame(
        [10, 11],
        1_700_000_000.5,
        4321,
        [_ndi_quaternion(), np.full(4, np.nan)],
        [TRANSLATION_MM, np.full(3, np.nan)],
        [0.12, np.nan],
    )
    readings = readings_from_ndi_frame(frame)
    assert [r.port_handle for r in readings] == [10, 11]
    expected_shape = (1, 7) if use_quaternions else (4, 4)
    assert readings[0].tracking.shape == expected_shape
    sample = sample_from_ndi_reading(readings[0])
    np.testing.assert_allclose(sample.translation_m, TRANSLATION_MM / 1000.0, atol=1e-12)
    np.testing.assert_allclose(sample.rotation, ROTATION.as_matrix(), atol=1e-12)
    assert sample.stamp_ns == 1_700_000_000_500_000_000
    assert sample.frame_number == 4321
    assert sample.quality == pytest.approx(0.12)
    assert sample.tool_id == "10"
    # the second tool is MISSING: NaN pose → rejected as not visible
    missing = sample_from_ndi_reading(readings[1])
    assert missing.status is ToolStatus.MISSING
    with pytest.raises(ToolNotVisibleError, match="'11' reported missing"):
        SampleGate().check(missing)


def test_ndi_dummy_tracker_frame_is_a_missing_tool(tmp_path):
    rom = tmp_path / "scope.rom"
    rom.write_bytes(b"\x00" * 16)
    tracker = NDITracker({"tracker type": "dummy", "romfiles": [str(rom)]})
    readings = readings_from_ndi_frame(tracker.get_frame())
    assert len(readings) == 1 and readings[0].tracking.shape == (4, 4)
    sample = sample_from_ndi_reading(readings[0])
    assert sample.status is ToolStatus.MISSING
    with pytest.raises(ToolNotVisibleError):
        SampleGate().check(sample)


def test_ndi_rejections():
    library = _LibraryFrames()
    frame = library.frame([1], 5.0, 7, [_ndi_quaternion()], [TRANSLATION_MM], [2.5])
    with pytest.raises(ToolNotVisibleError, match=r"fit error 2\.500 mm"):
        sample_from_ndi_reading(readings_from_ndi_frame(frame)[0], max_rms_error_mm=1.0)
    with pytest.raises(NdiFrameError, match="different lengths"):
        readings_from_ndi_frame(([1, 2], [0.0], [0], [np.eye(4)], [0.1]))
    with pytest.raises(NdiFrameError, match="5"):
        readings_from_ndi_frame(([1], [0.0]))
    partly = np.eye(4)
    partly[0, 3] = np.nan
    frame = ([1], [0.0], [3.0], [partly], [0.1])
    with pytest.raises(NonFinitePoseError):
        sample_from_ndi_reading(readings_from_ndi_frame(frame)[0])


def test_ndi_source_polls_the_tracker_and_reconnects_after_an_io_error():
    opened = []

    class FlakyTracker:
        def __init__(self, configuration):
            self.configuration = configuration
            self.frames = 0
            self.library = _LibraryFrames()
            opened.append(self)

        def start_tracking(self):
            pass

        def get_frame(self):
            self.frames += 1
            if len(opened) == 1 and self.frames > 3:
                raise OSError("serial port vanished")
            stamp = time.time()
            return self.library.frame(
                [1], stamp, self.frames, [_ndi_quaternion()], [TRANSLATION_MM], [0.1]
            )

        def close(self):
            pass

    options = NdiOptions(tracker_type="polaris", romfiles=("scope.rom",), rate_hz=200.0)
    source = NdiSource(options, open_tracker=FlakyTracker)
    woken = threading.Event()
    source.start(woken.set)
    deadline = time.monotonic() + 10.0
    items = []
    while time.monotonic() < deadline and (len(opened) < 2 or len(items) < 6):
        woken.wait(0.1)
        woken.clear()
        items += source.drain()
    source.stop()
    assert opened[0].configuration == {
        "tracker type": "polaris",
        "use quaternions": False,
        "romfiles": ["scope.rom"],
    }
    assert len(opened) >= 2, "the source did not reopen the tracker"
    samples = [source.to_sample(item) for item in items]
    np.testing.assert_allclose(samples[-1].translation_m, TRANSLATION_MM / 1000.0, atol=1e-12)


# -- CSV/TSV logs --------------------------------------------------------------------


def test_tab_separated_ndi_style_log(tmp_path):
    x, y, z, w = ROTATION.as_quat()
    path = tmp_path / "track.tsv"
    path.write_text(
        "# exported from NDI Track\n"
        "Time\tPort\tState\tFrame#\tQ0\tQx\tQy\tQz\tTx\tTy\tTz\tError\n"
        f"1700000000.016666667\t1\tOK\t100\t{w}\t{x}\t{y}\t{z}\t12.5\t-230.25\t-1405.0\t0.11\n"
        "1700000000.033333333\t1\tMissing\t101\t\t\t\t\t\t\t\t\n"
        f"1700000000.05\t1\tOK\t102\t{w}\t{x}\t{y}\t{z * 1.5}\t12.5\t-230.25\t-1405.0\t0.11\n"
        f"not-a-time\t1\tOK\t103\t{w}\t{x}\t{y}\t{z}\t12.5\t-230.25\t-1405.0\t0.11\n"
    )
    log = read_tracker_log(path)
    assert log.delimiter == "\t" and len(log.rows) == 4
    first = sample_from_log_row(log, 0, LengthUnit.MILLIMETRE)
    assert first.stamp_ns == 1_700_000_000_016_666_667  # exact decimal parsing
    np.testing.assert_allclose(first.translation_m, TRANSLATION_MM / 1000.0, atol=1e-15)
    np.testing.assert_allclose(first.rotation, ROTATION.as_matrix(), atol=1e-12)
    assert (first.tool_id, first.frame_number, first.quality) == ("1", 100, 0.11)
    assert sample_from_log_row(log, 1).status is ToolStatus.MISSING
    with pytest.raises(NonUnitQuaternionError):
        sample_from_log_row(log, 2)
    with pytest.raises(TrackerLogRowError, match="unreadable time"):
        sample_from_log_row(log, 3)


def test_comma_separated_matrix_log_in_metres(tmp_path):
    R = ROTATION.as_matrix()
    cells = [
        f"{float(R[i, j])!r}" if j < 3 else f"{[0.1, 0.2, 0.3][i]}"
        for i in range(3)
        for j in range(4)
    ]
    header = ",".join(["stamp_ns", "tool"] + [f"m{i}{j}" for i in range(3) for j in range(4)])
    path = tmp_path / "track.csv"
    path.write_text(f"{header}\n5000000000,scope,{','.join(cells)}\n")
    log = read_tracker_log(path)
    sample = sample_from_log_row(log, 0, LengthUnit.METRE)
    assert sample.stamp_ns == 5_000_000_000 and sample.tool_id == "scope"
    np.testing.assert_allclose(sample.translation_m, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(sample.rotation, R, atol=1e-15)


def test_log_without_pose_columns_is_refused(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("time,x,y,z\n0.0,1,2,3\n")
    with pytest.raises(TrackerLogError, match="qx"):
        read_tracker_log(path)
    with pytest.raises(TrackerLogError, match="cannot read"):
        read_tracker_log(tmp_path / "absent.csv")


def test_csv_replay_keeps_the_logs_own_stamps(tmp_path):
    lines = ["time_ns,tool,x,y,z,qx,qy,qz,qw"]
    lines += [
        f"{1_000_000_000 + i * 16_666_667},{'scope' if i % 2 == 0 else 'probe'},{i},0,0,0,0,0,1"
        for i in range(6)
    ]
    path = tmp_path / "track.csv"
    path.write_text("\n".join(lines) + "\n")
    source = CsvReplaySource(path, unit=LengthUnit.MILLIMETRE, tool="scope", rate=20.0)
    woken = threading.Event()
    source.start(woken.set)
    items: list[int] = []
    deadline = time.monotonic() + 5.0
    while len(items) < 3 and time.monotonic() < deadline:
        woken.wait(0.05)
        woken.clear()
        items += source.drain()
    source.stop()
    samples = [source.to_sample(i) for i in items]
    assert [s.stamp_ns for s in samples] == [1_000_000_000, 1_033_333_334, 1_066_666_668]
    np.testing.assert_allclose([s.translation_m[0] for s in samples], [0.0, 0.002, 0.004])
    assert source.status()["finished"] == "True"


def test_igtl_junk_stream_is_logged_throttled_and_connection_state_follows():
    # A peer that sends bytes that are not OpenIGTLink and hangs up, again and
    # again: the source reconnects each time but logs a few lines, not 2 a second.
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(0.2)
    port = listener.getsockname()[1]
    serving = threading.Event()
    serving.set()

    def serve() -> None:
        while serving.is_set():
            try:
                peer, _ = listener.accept()
            except TimeoutError:
                continue
            with peer:
                peer.sendall(b"\x00\x02" + b"JUNK" * 40)  # a header whose body size is huge

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    lines: list[str] = []
    source = IgtlSource(port=port, reconnect_interval_s=0.05, log=lines.append)
    source.start(lambda: None)
    try:
        time.sleep(1.5)
        assert source.connections >= 8
        assert 1 <= len(lines) <= 3, lines
        assert any("is not OpenIGTLink" in line for line in lines)
    finally:
        serving.clear()
        source.stop()
        server.join(2.0)
        listener.close()
    assert source.status()["connected"] == "False"
