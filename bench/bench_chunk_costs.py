"""What a recorder's chunk work costs per MB of a live graph's messages: compression and CRC.

    .venv/bin/python bench/bench_chunk_costs.py RECORDING [--megabytes 200] [--repeat 3]

RECORDING is a live graph's recording (``graph.mcap`` of a bench_graph run):
its messages are cut into chunks of 1 MiB (the BagWriter's ``chunk_size``),
in file order, and each chunk is compressed (zstd at level 3, what
``mcap``'s Python writer and so endo-record's default use; zstd at level 1,
libmcap's ``Default`` level; lz4 frame, endo-record's choice for the live
graph) and CRC-32'd (the chunk CRC, on in endo-record; rosbag2's MCAP plugin
writes uncompressed chunks without it by default). Reported: CPU ms
(process time) per MB of messages, the compression ratio, and so the CPU of
one frame of the graph at its MB per frame.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import lz4.frame
import zstandard

from endo_io.bag import BagReader
from endo_io.topics import IMAGE_CORRECTED

CHUNK_BYTES = 1 << 20


def chunks_of(recording: Path, megabytes: float) -> tuple[list[bytes], float]:
    """The recording's messages as 1 MiB chunks (up to ``megabytes``), and MB per graph frame."""
    chunks, current, total, frames = [], bytearray(), 0, 0
    with BagReader(recording) as reader:
        for message in reader.messages():
            current += message.data
            total += len(message.data)
            frames += message.topic == IMAGE_CORRECTED
            if len(current) >= CHUNK_BYTES:
                chunks.append(bytes(current))
                current = bytearray()
            if total >= megabytes * 1e6:
                break
    return chunks, total / 1e6 / max(frames, 1)


def cpu_ms_per_mb(work: Callable[[bytes], object], chunks: list[bytes], repeat: int) -> float:
    """Median over ``repeat`` passes of the CPU ms ``work`` takes per MB of ``chunks``."""
    size_mb = sum(len(c) for c in chunks) / 1e6
    passes = []
    for _ in range(repeat):
        start = time.process_time()
        for chunk in chunks:
            work(chunk)
        passes.append(1e3 * (time.process_time() - start) / size_mb)
    return statistics.median(passes)


def main() -> int:
    """Print the table of per-MB costs."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", type=Path)
    parser.add_argument("--megabytes", type=float, default=200.0)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    chunks, mb_per_frame = chunks_of(args.recording, args.megabytes)
    size = sum(len(c) for c in chunks)
    zstd3, zstd1 = zstandard.ZstdCompressor(level=3), zstandard.ZstdCompressor(level=1)
    ways: dict[str, Callable[[bytes], bytes]] = {
        "zstd level 3": zstd3.compress, "zstd level 1": zstd1.compress,
        "lz4 frame": lz4.frame.compress,
    }
    print(f"{args.recording}: {len(chunks)} chunks, {size / 1e6:.0f} MB, "
          f"{mb_per_frame:.2f} MB per graph frame")
    print("| work | CPU ms per MB | ratio | CPU ms per graph frame |")
    print("|---|---|---|---|")
    for name, compress in ways.items():
        ratio = size / sum(len(compress(c)) for c in chunks)
        ms = cpu_ms_per_mb(compress, chunks, args.repeat)
        print(f"| {name} | {ms:.2f} | {ratio:.2f} | {ms * mb_per_frame:.2f} |")
    ms = cpu_ms_per_mb(zlib.crc32, chunks, args.repeat)
    print(f"| chunk CRC-32 | {ms:.2f} | – | {ms * mb_per_frame:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
