"""rosbag2 bag metadata: the ``metadata.yaml`` of a bag directory and the ``rosbag2`` MCAP record.

rosbag2 describes a bag with a ``BagMetadata`` structure (version 9 in
Jazzy). It is stored twice:

* in ``<bag dir>/metadata.yaml`` under the key ``rosbag2_bagfile_information``;
  this is how ``ros2 bag`` and rosbags find the files of a split bag
  (``relative_file_paths``), in order;
* inside each MCAP file, as a Metadata record named ``rosbag2`` whose single
  key ``serialized_metadata`` holds the same structure as YAML (without the
  outer key). rosbag2_storage_mcap writes it when the file is closed, so a
  lone ``.mcap`` still says what it is.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from endo_io.bag.errors import BagError, BagNotFoundError
from endo_io.bag.qos_yaml import qos_dicts_from_yaml

#: Name of the MCAP Metadata record that rosbag2 writes.
ROSBAG2_METADATA_RECORD = "rosbag2"
#: Key of that record holding the YAML.
SERIALIZED_METADATA_KEY = "serialized_metadata"
#: rosbag2 metadata version written here (Jazzy).
METADATA_VERSION = 9
METADATA_FILENAME = "metadata.yaml"
_TOP_KEY = "rosbag2_bagfile_information"


@dataclass(frozen=True)
class TopicSummary:
    """One topic of a bag as metadata.yaml lists it.

    Attributes:
        name: Topic name.
        msgtype: ROS 2 type name.
        serialization_format: ``cdr``.
        offered_qos_profiles: rosbag2 QoS YAML string ("" if none).
        type_description_hash: ``RIHS01_...`` or "".
        message_count: Messages on this topic.
    """

    name: str
    msgtype: str
    serialization_format: str
    offered_qos_profiles: str
    type_description_hash: str
    message_count: int


@dataclass(frozen=True)
class FileSummary:
    """One MCAP file of a bag.

    Attributes:
        path: File name relative to the bag directory.
        starting_time_ns: Earliest log time in the file, ns (0 if empty).
        duration_ns: Latest minus earliest log time, ns.
        message_count: Messages in the file.
    """

    path: str
    starting_time_ns: int
    duration_ns: int
    message_count: int


class _Rosbag2Dumper(yaml.SafeDumper):
    """Indents block sequences inside mappings, as yaml-cpp (rosbag2) does."""

    def increase_indent(self, flow: bool = False, indentless: bool = False) -> None:
        super().increase_indent(flow, False)


def bag_metadata(
    topics: Sequence[TopicSummary],
    files: Sequence[FileSummary],
    *,
    ros_distro: str | None = None,
) -> dict[str, Any]:
    """Build the rosbag2 ``BagMetadata`` mapping (version 9) for MCAP files.

    Start time and duration span all files; counts are summed.
    """
    nonempty = [f for f in files if f.message_count > 0]
    start = min((f.starting_time_ns for f in nonempty), default=0)
    end = max((f.starting_time_ns + f.duration_ns for f in nonempty), default=0)
    return {
        "version": METADATA_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": end - start},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": sum(f.message_count for f in files),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": t.name,
                    "type": t.msgtype,
                    "serialization_format": t.serialization_format,
                    "offered_qos_profiles": qos_dicts_from_yaml(t.offered_qos_profiles),
                    "type_description_hash": t.type_description_hash,
                },
                "message_count": t.message_count,
            }
            for t in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [f.path for f in files],
        "files": [
            {
                "path": f.path,
                "starting_time": {"nanoseconds_since_epoch": f.starting_time_ns},
                "duration": {"nanoseconds": f.duration_ns},
                "message_count": f.message_count,
            }
            for f in files
        ],
        "custom_data": None,
        "ros_distro": ros_distro or os.environ.get("ROS_DISTRO", "jazzy"),
    }


def dump_bag_metadata(metadata: dict[str, Any]) -> str:
    """YAML of a ``BagMetadata`` mapping, as stored in the ``rosbag2`` MCAP record."""
    return yaml.dump(metadata, Dumper=_Rosbag2Dumper, sort_keys=False, default_flow_style=False)


def write_metadata_yaml(directory: Path, metadata: dict[str, Any]) -> Path:
    """Write ``<directory>/metadata.yaml`` atomically (write a temp file, then rename)."""
    path = directory / METADATA_FILENAME
    tmp = directory / (METADATA_FILENAME + ".tmp")
    tmp.write_text(dump_bag_metadata({_TOP_KEY: metadata}), encoding="utf-8")
    tmp.replace(path)
    return path


def read_metadata_yaml(directory: Path) -> dict[str, Any]:
    """Read the ``BagMetadata`` mapping of a bag directory.

    Raises:
        BagNotFoundError: there is no metadata.yaml in ``directory``.
        BagError: it is not rosbag2 metadata, or names no files.
    """
    path = directory / METADATA_FILENAME
    if not path.is_file():
        found = sorted(p.name for p in directory.glob("*.mcap"))
        hint = f" (it holds {', '.join(found)}: open a file directly)" if found else ""
        raise BagNotFoundError(
            f"{directory}: not a rosbag2 directory, no {METADATA_FILENAME}{hint}"
        )
    try:
        loaded = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise BagError(f"{path}: unreadable metadata ({str(exc).splitlines()[0]})") from exc
    if not isinstance(loaded, dict) or not isinstance(loaded.get(_TOP_KEY), dict):
        raise BagError(f"{path}: no '{_TOP_KEY}' mapping, not rosbag2 metadata")
    metadata: dict[str, Any] = loaded[_TOP_KEY]
    paths = metadata.get("relative_file_paths")
    if not isinstance(paths, list) or not paths or not all(isinstance(p, str) for p in paths):
        raise BagError(f"{path}: 'relative_file_paths' lists no files")
    return metadata


def split_file_order(path: Path) -> tuple[int, str]:
    """Sort key of a bag directory's files: rosbag2 names them ``<bag>_<n>.mcap``, by ``n``."""
    match = re.search(r"_(\d+)$", path.stem)
    return (int(match.group(1)) if match else -1, path.name)


def parse_bag_metadata(text: str) -> dict[str, Any] | None:
    """Parse the YAML of a ``rosbag2`` MCAP record; None if it is not a mapping."""
    try:
        loaded = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    return loaded if isinstance(loaded, dict) else None
