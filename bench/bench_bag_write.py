"""The MCAP writer's CPU per frame, this tree's BagWriter against a baseline's, in one process.

    .venv/bin/python bench/bench_bag_write.py BAG --baseline WRITER_PY [--repeat 5]
        [--compression lz4] [--flush-period 0.2]

The messages of BAG (every topic, as recorded) are read into memory once and
then written into a new file, alternately by this tree's
:class:`endo_io.bag.BagWriter` and by the one in ``WRITER_PY`` (a baseline's
``endo_io/bag/writer.py``, e.g. ``git show main:src/endo_io/endo_io/bag/writer.py
> /tmp/base_writer.py``), as endo-record writes them: chunks of the writer's
default size, ``--compression`` (lz4: the live graph's recorder), a flush
every ``--flush-period`` seconds of log time. Reported: process CPU time per
image frame of the bag (the first image topic's messages) for each, median
over the repeats, and their ratio; the two alternate, so that load changes
fall on both.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

from endo_io.bag import BagReader, BagWriter

NS_PER_S = 1_000_000_000


def load_writer(path: Path) -> ModuleType:
    """The module at ``path`` (a writer.py), imported under a name of its own."""
    spec = importlib.util.spec_from_file_location("baseline_bag_writer", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look themselves up there
    spec.loader.exec_module(module)
    return module


def write_all(writer_class: type, target: Path, topics: list[tuple[str, str, str]],
              messages: list[tuple[str, bytes, int, int]], compression: str,
              flush_period_ns: int) -> float:
    """Write ``messages`` into ``target``; returns the process CPU seconds it took."""
    began = time.process_time()
    writer = writer_class(target, compression=compression)
    for name, msgtype, qos in topics:
        writer.add_topic(name, msgtype, qos)
    next_flush = messages[0][2] + flush_period_ns
    for topic, data, log_ns, publish_ns in messages:
        writer.write(topic, data, log_ns, publish_ns)
        if log_ns >= next_flush:
            writer.flush()
            next_flush = log_ns + flush_period_ns
    writer.close()
    return time.process_time() - began


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("--baseline", type=Path, required=True, metavar="WRITER_PY")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--compression", default="lz4")
    parser.add_argument("--flush-period", type=float, default=0.2)
    args = parser.parse_args()
    baseline = load_writer(args.baseline).BagWriter
    with BagReader(args.bag) as reader:
        infos = reader.topics
        topics = [(name, info.msgtype, info.offered_qos_profiles)
                  for name, info in infos.items()]
        messages = [(m.topic, bytes(m.data), m.log_time_ns, m.publish_time_ns)
                    for m in reader.messages()]
    image_topic = next(name for name, msgtype, _ in topics if msgtype == "sensor_msgs/msg/Image")
    frames = sum(1 for m in messages if m[0] == image_topic)
    megabytes = sum(len(m[1]) for m in messages) / 1e6
    costs: dict[str, list[float]] = {"this tree": [], "baseline": []}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeat):
            for name, writer_class in (("this tree", BagWriter), ("baseline", baseline)):
                target = Path(tmp) / f"{name.replace(' ', '_')}_{k}.mcap"
                seconds = write_all(writer_class, target, topics, messages, args.compression,
                                    round(args.flush_period * NS_PER_S))
                costs[name].append(seconds * 1e3 / frames)
                target.unlink()
    ours, base = (statistics.median(costs[n]) for n in ("this tree", "baseline"))
    print(f"bench_bag_write: {args.bag.name}, {len(messages)} messages, {megabytes:.1f} MB, "
          f"{frames} frames of {image_topic}; {args.compression}, flush every "
          f"{args.flush_period:g} s; {args.repeat} alternating repeats")
    for name, values in costs.items():
        print(f"  {name}: CPU ms per frame median {statistics.median(values):.3f} "
              f"(runs {', '.join(f'{v:.3f}' for v in values)})")
    print(f"  this tree / baseline: {ours / base:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
