"""A writer killed with SIGKILL leaves a bag that reads up to the last chunk written."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import pytest
from std_msgs.msg import Float32

from endo_io.bag import BagCorruptError, BagReader, deserialize

# Writes 40 small messages (chunks close by size as they fill), reports, waits;
# then flushes, writes 3 more that stay in the open chunk, reports, sleeps.
CHILD = textwrap.dedent(
    """
    import sys, time
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float32
    from endo_io.bag import BagWriter

    writer = BagWriter(sys.argv[1], compression=sys.argv[2], chunk_size=512)
    writer.add_topic("/value", "std_msgs/msg/Float32")
    for i in range(40):
        writer.write("/value", serialize_message(Float32(data=float(i))), 1_000 + i)
    print("filled", flush=True)
    sys.stdin.readline()
    writer.flush()
    for i in range(40, 43):
        writer.write("/value", serialize_message(Float32(data=float(i))), 1_000 + i)
    print("flushed", flush=True)
    time.sleep(120)
    """
)


def read_values(path) -> tuple[list[float], BagCorruptError | None]:
    values: list[float] = []
    try:
        with BagReader(path) as reader:
            for message in reader.messages():
                values.append(deserialize(message).data)
    except BagCorruptError as exc:
        return values, exc
    return values, None


@pytest.mark.parametrize(("name", "compression"), [("rec.mcap", "zstd"), ("rec_dir", "lz4")])
def test_sigkilled_writer_leaves_a_readable_bag(tmp_path, name, compression):
    target = tmp_path / name
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(target), compression],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )
    try:
        assert child.stdout is not None and child.stdin is not None
        assert child.stdout.readline().strip() == "filled"
        # A copy taken while the writer runs holds every chunk closed so far.
        mcap_path = target if target.suffix == ".mcap" else target / "rec_dir_0.mcap"
        snapshot = tmp_path / "snapshot.mcap"
        snapshot.write_bytes(mcap_path.read_bytes())
        values, error = read_values(snapshot)
        assert 30 <= len(values) < 40  # only the open chunk (< 512 bytes) is missing
        assert values == [float(i) for i in range(len(values))]
        assert error is not None
        child.stdin.write("\n")
        child.stdin.flush()
        assert child.stdout.readline().strip() == "flushed"
        os.kill(child.pid, signal.SIGKILL)
        assert child.wait(timeout=30) == -signal.SIGKILL
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    values, error = read_values(target)
    assert values == [float(i) for i in range(40)]  # 40..42 never left the process
    assert error is not None and "byte" in str(error)
    with BagReader(target) as reader:
        assert reader.topics["/value"].message_count == 40
        if target.suffix != ".mcap":
            # metadata.yaml is rewritten at each flush: it counts the 40 on disk, not 0.
            assert reader.metadata is not None and reader.metadata["message_count"] == 40
            assert reader.warnings == []
        assert reader.topics["/value"].msgtype == "std_msgs/msg/Float32"
    assert Float32(data=39.0) == Float32(data=values[-1])
