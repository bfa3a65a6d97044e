"""rosbag2-compatible MCAP bags: read, write, (de)serialise.

>>> with BagWriter("run.mcap") as bag:
...     bag.write_message("/camera/image_raw", image_msg, log_time_ns)
>>> with BagReader("run.mcap") as bag:
...     for message in bag.messages(topics=["/camera/image_raw"]):
...         image = deserialize(message)

Files follow rosbag2's MCAP storage (``ros2`` profile, complete ``ros2msg``
schemas, ``cdr``, QoS offers in channel metadata, the ``rosbag2`` metadata
record), so ``ros2 bag``, rosbags and mcap-ros2-support read them, and we
read theirs. See docs/bag_format.md.
"""

from endo_io.bag.errors import (
    BagCorruptError,
    BagError,
    BagNotFoundError,
    MessageDeserializationError,
    TopicTypeError,
    UnknownMessageTypeError,
)
from endo_io.bag.interfaces import BagMessage, DamagedRegion, LostMessages, TopicInfo
from endo_io.bag.msgdef import MessageDefinition, message_definition, type_description_hash
from endo_io.bag.qos_yaml import QosYamlError, qos_profiles_from_yaml, qos_profiles_to_yaml
from endo_io.bag.reader import BagReader
from endo_io.bag.serde import deserialize, message_class, msgtype_of, serialize
from endo_io.bag.writer import BagWriter

__all__ = [
    "BagCorruptError",
    "BagError",
    "BagMessage",
    "BagNotFoundError",
    "BagReader",
    "BagWriter",
    "DamagedRegion",
    "LostMessages",
    "MessageDefinition",
    "MessageDeserializationError",
    "QosYamlError",
    "TopicInfo",
    "TopicTypeError",
    "UnknownMessageTypeError",
    "deserialize",
    "message_class",
    "message_definition",
    "msgtype_of",
    "qos_profiles_from_yaml",
    "qos_profiles_to_yaml",
    "serialize",
    "type_description_hash",
]
