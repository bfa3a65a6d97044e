"""Complete message definitions (MCAP schema text) from the installed interface files.

A rosbag2 MCAP schema carries the *complete* definition of a type: its own
``.msg`` text followed by the text of every type it uses, recursively, so that
a tool without our packages installed (Foxglove, rosbags, mcap-ros2-support)
can still decode the bag. The text is built exactly as rosbag2's
``LocalMessageDefinitionSource`` builds it:

* ``ros2msg``: the root ``.msg`` file as installed, then for each dependency
  (in sorted order, depth first, each type once) a newline, a line of 80
  ``=``, a line ``MSG: <type as written in the field>`` (usually
  ``pkg/Name``) and that type's ``.msg`` text;
* ``ros2idl`` (types with no ``.msg``, e.g. service events): every ``.idl``
  preceded by an 80-``=`` line and ``IDL: pkg/msg/Name``.

Interface files are found under ``<prefix>/share/<pkg>/<msg|srv|action>/``
for each prefix in ``AMENT_PREFIX_PATH`` and then ``sys.prefix`` (the ROS 2
wheels install them under the virtualenv's ``share/``, and a venv has no
``AMENT_PREFIX_PATH`` unless a setup script was sourced).
"""

from __future__ import annotations

import functools
import json
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from endo_io.bag.errors import UnknownMessageTypeError

#: Line that separates the definitions of a complete message definition.
DEFINITION_SEPARATOR = "=" * 80

# Same patterns as rosbag2_cpp: the first token of each .msg line is the field
# type; IDL dependencies are the #include lines.
_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_IDL_INCLUDE = re.compile(r"(?:^|\n)#include\s+(?:\"|<)([a-zA-Z0-9_/]+)\.idl(?:\"|>)")
_PRIMITIVE_TYPES = frozenset(
    {
        "bool", "byte", "char", "float32", "float64", "int8", "uint8",
        "int16", "uint16", "int32", "uint32", "int64", "uint64", "string",
    }
)  # fmt: skip
_ROS_NAME = r"[a-zA-Z][a-zA-Z0-9_]*"
_TYPE_NAME = re.compile(rf"^({_ROS_NAME})/(?:({_ROS_NAME})/)?({_ROS_NAME})$")


@dataclass(frozen=True)
class MessageDefinition:
    """A complete message definition as stored in an MCAP Schema record.

    Attributes:
        encoding: ``ros2msg``, ``ros2idl``, or ``unknown`` (no definition found;
            ``text`` is then empty), as rosbag2 writes it.
        text: The complete definition text.
    """

    encoding: str
    text: str


def split_msgtype(msgtype: str) -> tuple[str, str, str]:
    """Split ``pkg/msg/Name`` (or the short ``pkg/Name``) into (package, namespace, name).

    Raises:
        UnknownMessageTypeError: ``msgtype`` is not a ROS 2 type name.
    """
    match = _TYPE_NAME.match(msgtype)
    if match is None:
        raise UnknownMessageTypeError(f"not a ROS 2 message type name: {msgtype!r}")
    package, namespace, name = match.groups()
    return package, namespace or "msg", name


def interface_prefixes() -> list[Path]:
    """Prefixes searched for ``share/<pkg>/``: AMENT_PREFIX_PATH entries, then sys.prefix."""
    prefixes = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(Path(sys.prefix))
    return prefixes


@functools.lru_cache(maxsize=1024)
def find_interface_file(package: str, namespace: str, name: str, extension: str) -> Path | None:
    """Return ``share/<package>/<namespace>/<name><extension>`` of the first prefix that has it."""
    for prefix in interface_prefixes():
        candidate = prefix / "share" / package / namespace / f"{name}{extension}"
        if candidate.is_file():
            return candidate
    return None


def _read_definition(type_name: str, extension: str) -> tuple[str, str] | None:
    """Return (text, package) of one interface file, or None if it is not installed."""
    package, namespace, name = split_msgtype(type_name)
    path = find_interface_file(package, namespace, name, extension)
    if path is None:
        return None
    return path.read_text(encoding="utf-8"), package


def _dependencies(text: str, package: str, extension: str) -> list[str]:
    """Types referenced by one definition, sorted as rosbag2's std::set sorts them."""
    if extension == ".msg":
        found = set()
        for match in _MSG_FIELD_TYPE.finditer(text):
            field_type = match.group(1)
            if field_type in _PRIMITIVE_TYPES:
                continue
            found.add(field_type if "/" in field_type else f"{package}/{field_type}")
        return sorted(found)
    return sorted({m.group(1) for m in _IDL_INCLUDE.finditer(text)})


def _complete_text(root: str, extension: str, root_text: str, root_package: str) -> str:
    label = "MSG: " if extension == ".msg" else "IDL: "
    seen: set[str] = set()

    def append(text: str, package: str, depth: int) -> str:
        if depth <= 0:
            raise UnknownMessageTypeError(f"definition of {root} nests too deeply")
        result = text
        for dependency in _dependencies(text, package, extension):
            if dependency in seen:
                continue
            seen.add(dependency)
            loaded = _read_definition(dependency, extension)
            if loaded is None:
                raise UnknownMessageTypeError(
                    f"definition of {dependency} (used by {root}) is not installed"
                )
            result += f"\n{DEFINITION_SEPARATOR}\n{label}{dependency}\n"
            result += append(loaded[0], loaded[1], depth - 1)
        return result

    return append(root_text, root_package, 50)


@functools.lru_cache(maxsize=256)
def message_definition(msgtype: str) -> MessageDefinition:
    """Complete definition of ``msgtype`` from the installed interface files.

    Uses the ``.msg`` files when the type has one (``ros2msg``), else the
    ``.idl`` files (``ros2idl``); a type that is not installed at all, or
    whose dependencies are missing, gives ``MessageDefinition("unknown", "")``
    as rosbag2 records it.
    """
    try:
        package, namespace, name = split_msgtype(msgtype)
        full_name = f"{package}/{namespace}/{name}"
        loaded = _read_definition(full_name, ".msg")
        if loaded is not None:
            return MessageDefinition("ros2msg", _complete_text(full_name, ".msg", *loaded))
        loaded = _read_definition(full_name, ".idl")
        if loaded is not None:
            text = _complete_text(full_name, ".idl", *loaded)
            return MessageDefinition("ros2idl", f"{DEFINITION_SEPARATOR}\nIDL: {full_name}\n{text}")
    except UnknownMessageTypeError:
        pass
    return MessageDefinition("unknown", "")


@functools.lru_cache(maxsize=256)
def type_description_hash(msgtype: str) -> str:
    """``RIHS01_<sha256>`` type hash of an installed type (from its ``.json``), or "" if unknown."""
    try:
        package, namespace, name = split_msgtype(msgtype)
    except UnknownMessageTypeError:
        return ""
    path = find_interface_file(package, namespace, name, ".json")
    if path is None:
        return ""
    try:
        hashes = json.loads(path.read_text(encoding="utf-8"))["type_hashes"]
    except (OSError, ValueError, KeyError, TypeError):
        return ""
    full_name = f"{package}/{namespace}/{name}"
    for entry in hashes:
        if isinstance(entry, dict) and entry.get("type_name") == full_name:
            return str(entry.get("hash_string", ""))
    return ""
