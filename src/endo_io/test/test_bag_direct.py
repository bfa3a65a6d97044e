"""BagWriter(direct=True): the same file as a buffered writer, the same failures.

``O_DIRECT`` writes whole aligned blocks from a page-aligned stage and the
file's last partial block through the ordinary descriptor
(:class:`endo_io.bag.writer._DirectWrites`). Messages of every size around
the alignment and past the stage's first size, flushes, a file system that
refuses ``O_DIRECT``, a disk that fills up and a SIGKILL must leave exactly
what a buffered writer leaves.
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import numpy as np
import pytest

from endo_io.bag import BagCorruptError, BagError, BagReader, BagWriter
from endo_io.bag import writer as writer_module

T0 = 1_700_000_000_000_000_000
ALIGN = writer_module.DIRECT_ALIGNMENT


def direct_supported(directory: Path) -> bool:
    """Whether ``directory``'s file system takes an aligned ``O_DIRECT`` write."""
    probe = directory / "probe.bin"
    probe.touch()
    try:
        fd = os.open(probe, os.O_WRONLY | getattr(os, "O_DIRECT", 0))
    except OSError:
        return False
    try:
        import mmap

        block = mmap.mmap(-1, ALIGN)
        os.pwrite(fd, block, 0)
        block.close()
        return bool(getattr(os, "O_DIRECT", 0))
    except OSError:
        return False
    finally:
        os.close(fd)
        probe.unlink()


def messages() -> list[tuple[str, bytes]]:
    """Sizes around the alignment, odd sizes, and two past the 4 MB stage."""
    rng = np.random.default_rng(7)
    sizes = [
        1,
        7,
        ALIGN - 30,
        ALIGN,
        ALIGN + 1,
        3 * ALIGN - 1,
        100_003,
        1_228_845,
        614_445,
        5_000_001,
        17,
        9 << 20,
        2 * ALIGN,
        333,
    ]
    sizes += [int(s) for s in rng.integers(1, 300_000, 40)]
    return [(f"/t{k % 3}", rng.bytes(size)) for k, size in enumerate(sizes)]


def write_bag(path: Path, direct: bool, compression: str = "none") -> BagWriter:
    writer = BagWriter(path, compression=compression, crcs=False, direct=direct)
    for topic in ("/t0", "/t1", "/t2"):
        writer.add_topic(topic, "std_msgs/msg/UInt8MultiArray")
    for k, (topic, data) in enumerate(messages()):
        writer.write(topic, data, T0 + k)
        if k % 7 == 6:
            writer.flush()
    return writer


@pytest.mark.parametrize("target", ["run.mcap", "run_dir"])
@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_direct_writes_make_the_same_file_byte_for_byte(tmp_path, target, compression):
    if not direct_supported(tmp_path):
        pytest.skip("this file system takes no O_DIRECT writes")
    files = []
    for direct in (False, True):
        root = tmp_path / str(direct)
        root.mkdir()
        writer = write_bag(root / target, direct, compression)
        assert writer._sink is not None
        assert (writer._sink._direct is not None) == direct  # the O_DIRECT path ran
        writer.close()
        folder = root if target.endswith(".mcap") else root / target
        files.append(folder / ("run.mcap" if target.endswith(".mcap") else "run_dir_0.mcap"))
    assert files[0].read_bytes() == files[1].read_bytes()
    with BagReader(files[1]) as reader:
        got = [(m.topic, bytes(m.data)) for m in reader.messages()]
    assert got == messages()


def test_a_file_system_that_refuses_o_direct_writes_gets_a_buffered_file(tmp_path, monkeypatch):
    refused = []

    def pwrite(fd: int, data, offset: int) -> int:
        refused.append(offset)
        raise OSError(errno.EINVAL, os.strerror(errno.EINVAL))

    refusing = types.SimpleNamespace(**{**vars(os), "pwrite": pwrite})
    monkeypatch.setattr(writer_module, "os", refusing)
    for name in ("direct", "buffered"):  # the same file name: the metadata record holds it
        (tmp_path / name).mkdir()
    writer = write_bag(tmp_path / "direct" / "run.mcap", True)
    assert writer._sink is not None and writer._sink._direct is None  # given up after one refusal
    writer.close()
    monkeypatch.undo()
    assert len(refused) == 1
    write_bag(tmp_path / "buffered" / "run.mcap", False).close()
    assert (tmp_path / "direct" / "run.mcap").read_bytes() == (
        tmp_path / "buffered" / "run.mcap"
    ).read_bytes()


class SizeLimit:
    """``os.write`` and ``os.pwrite`` on a disk that holds ``limit`` bytes of the file."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.failures = 0

    def _allowed(self, data, offset: int) -> memoryview:
        room = self.limit - offset
        if room <= 0:
            self.failures += 1
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return memoryview(data)[:room]

    def write(self, fd: int, data) -> int:
        return os.write(fd, self._allowed(data, os.lseek(fd, 0, os.SEEK_CUR)))

    def pwrite(self, fd: int, data, offset: int) -> int:
        return os.pwrite(fd, self._allowed(data, offset), offset)


@pytest.mark.parametrize("limit", [5_000, 2 * ALIGN + 100, 1_300_000, 6_000_000])
def test_on_a_full_disk_a_direct_writer_keeps_what_it_counts(tmp_path, monkeypatch, limit):
    if not direct_supported(tmp_path):
        pytest.skip("this file system takes no O_DIRECT writes")
    disk = SizeLimit(limit)
    monkeypatch.setattr(writer_module, "os", types.SimpleNamespace(
        **{**vars(os), "write": disk.write, "pwrite": disk.pwrite}))  # fmt: skip
    path = tmp_path / "full.mcap"
    writer = BagWriter(path, compression="none", crcs=False, direct=True, chunk_size=50_000)
    writer.add_topic("/t", "std_msgs/msg/UInt8MultiArray")
    sent = []
    error = ""
    for k, (_, data) in enumerate(messages()):
        try:
            writer.write("/t", data, T0 + k)
            sent.append(data)
            if k % 5 == 4:
                writer.flush()
        except BagError as exc:
            sent.append(data)
            error = str(exc)
            break
    assert "disk full" in error and disk.failures >= 1
    written, _ = writer.written["/t"]
    writer.close()
    monkeypatch.undo()
    got: list[bytes] = []
    with (
        pytest.raises(BagCorruptError, match="ends before the MCAP footer"),
        BagReader(path) as reader,
    ):
        for message in reader.messages():
            got.append(bytes(message.data))
    assert got == sent[:written]  # exactly what it counted, a prefix of what was sent
    assert path.stat().st_size <= limit


CHILD = textwrap.dedent(
    """
    import sys, time
    from endo_io.bag import BagWriter

    writer = BagWriter(sys.argv[1], compression="none", chunk_size=3000, crcs=False, direct=True)
    writer.add_topic("/t", "std_msgs/msg/UInt8MultiArray")
    for i in range(40):
        writer.write("/t", bytes([i]) * (1000 + 97 * i), 1_000 + i)
    writer.flush()
    writer.write("/t", b"open chunk", 2_000)
    print("flushed", flush=True)
    time.sleep(120)
    """
)


def test_a_sigkilled_direct_writer_leaves_every_chunk_it_wrote(tmp_path):
    if not direct_supported(tmp_path):
        pytest.skip("this file system takes no O_DIRECT writes")
    path = tmp_path / "killed.mcap"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE,
                             text=True)  # fmt: skip
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "flushed"
        os.kill(child.pid, signal.SIGKILL)
        assert child.wait(timeout=30) == -signal.SIGKILL
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    got: list[bytes] = []
    with pytest.raises(BagCorruptError), BagReader(path) as reader:
        for message in reader.messages():
            got.append(bytes(message.data))
    assert got == [bytes([i]) * (1000 + 97 * i) for i in range(40)]
