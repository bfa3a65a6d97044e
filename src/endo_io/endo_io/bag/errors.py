"""Named errors of the bag reader and writer.

:class:`endo_io.errors.BagError` and :class:`endo_io.errors.BagCorruptError`
are the shared base classes; the classes here say more precisely what was
wrong, so that a caller can react to the class alone.
"""

from __future__ import annotations

from endo_io.errors import BagCorruptError, BagError

__all__ = [
    "BagCorruptError",
    "BagError",
    "BagNotFoundError",
    "MessageDeserializationError",
    "TopicTypeError",
    "UnknownMessageTypeError",
]


class BagNotFoundError(BagError, FileNotFoundError):
    """A bag file, a split-bag member file or a bag's metadata.yaml does not exist."""


class UnknownMessageTypeError(BagError):
    """A message type is not installed (or not a ROS message), so it cannot be (de)serialised."""


class MessageDeserializationError(BagError):
    """A message's CDR bytes do not decode as the installed definition of its type."""


class TopicTypeError(BagError):
    """A topic holds another message type than the one a tool reads from it."""
