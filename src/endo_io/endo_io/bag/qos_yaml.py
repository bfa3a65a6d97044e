"""Offered QoS profiles in rosbag2's YAML form, to and from rclpy ``QoSProfile``.

rosbag2 stores, per topic, the QoS profiles that the recorded publishers
offered (MCAP channel metadata ``offered_qos_profiles``; a list in
metadata.yaml), so that ``ros2 bag play`` can offer the same again: a
transient-local (latched) calibration topic stays latched on replay, and a
best-effort camera stays best effort.

Format (rosbag2 metadata version 9, Jazzy): a YAML sequence with one mapping
per publisher, policies as lower-case names, durations as ``{sec, nsec}``::

    - history: keep_last
      depth: 10
      reliability: reliable
      durability: volatile
      deadline:
        sec: 9223372036
        nsec: 854775807
      ...

Parsing also accepts version-8 bags (policies as integers) and the "infinite"
durations that Foxy-era RMWs wrote.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import yaml
from rclpy.duration import Duration
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

from endo_io.bag.errors import BagError

NS_PER_S = 1_000_000_000
#: RMW_DURATION_INFINITE (int64 max nanoseconds) as rosbag2 writes it.
INFINITE_SEC, INFINITE_NSEC = divmod(2**63 - 1, NS_PER_S)
# "Infinite" as recorded by Foxy-era RMWs (CycloneDDS, Fast DDS, Connext);
# rosbag2 maps them to RMW_DURATION_INFINITE when reading.
_LEGACY_INFINITE = {
    (INFINITE_SEC, INFINITE_NSEC),
    (0x7FFFFFFF, 0xFFFFFFFF),
    (0x7FFFFFFF, 0x7FFFFFFF),
}


class QosYamlError(BagError):
    """An ``offered_qos_profiles`` text is not a rosbag2 QoS profile list."""


def _duration_to_yaml(duration: Duration) -> dict[str, int]:
    ns = int(duration.nanoseconds)
    if ns >= 2**63 - 1:
        return {"sec": INFINITE_SEC, "nsec": INFINITE_NSEC}
    sec, nsec = divmod(ns, NS_PER_S)
    return {"sec": sec, "nsec": nsec}


def _duration_from_yaml(node: Any, key: str) -> Duration:
    try:
        sec, nsec = int(node["sec"]), int(node["nsec"])
    except (TypeError, KeyError, ValueError) as exc:
        raise QosYamlError(f"QoS {key} is not a {{sec, nsec}} mapping: {node!r}") from exc
    if (sec, nsec) in _LEGACY_INFINITE:
        return Duration(nanoseconds=2**63 - 1)
    return Duration(nanoseconds=sec * NS_PER_S + nsec)


def qos_profile_to_dict(profile: QoSProfile) -> dict[str, Any]:
    """One profile as the rosbag2 (version 9) mapping, keys in rosbag2's order."""
    return {
        "history": profile.history.short_key,
        "depth": int(profile.depth),
        "reliability": profile.reliability.short_key,
        "durability": profile.durability.short_key,
        "deadline": _duration_to_yaml(profile.deadline),
        "lifespan": _duration_to_yaml(profile.lifespan),
        "liveliness": profile.liveliness.short_key,
        "liveliness_lease_duration": _duration_to_yaml(profile.liveliness_lease_duration),
        "avoid_ros_namespace_conventions": bool(profile.avoid_ros_namespace_conventions),
    }


def _policy(enum: Any, value: Any, key: str) -> Any:
    if isinstance(value, bool):
        raise QosYamlError(f"QoS {key} {value!r} is not a policy")
    if isinstance(value, int):  # metadata version <= 8
        try:
            return enum(value)
        except ValueError:
            return enum.UNKNOWN
    if isinstance(value, str):
        for member in enum:
            if member.short_key == value.lower():
                return member
        return enum.UNKNOWN
    raise QosYamlError(f"QoS {key} {value!r} is not a policy name or number")


def qos_profile_from_dict(node: Mapping[str, Any]) -> QoSProfile:
    """Parse one rosbag2 QoS mapping (version 8 or 9) into an rclpy ``QoSProfile``.

    Raises:
        QosYamlError: a policy or duration is missing or malformed.
    """
    if not isinstance(node, Mapping):
        raise QosYamlError(f"QoS profile is not a mapping: {node!r}")
    try:
        history = _policy(HistoryPolicy, node["history"], "history")
        depth = int(node.get("depth", 0))
        profile = QoSProfile(
            history=history,
            depth=depth,
            reliability=_policy(ReliabilityPolicy, node["reliability"], "reliability"),
            durability=_policy(DurabilityPolicy, node["durability"], "durability"),
            liveliness=_policy(LivelinessPolicy, node["liveliness"], "liveliness"),
            deadline=_duration_from_yaml(node["deadline"], "deadline"),
            lifespan=_duration_from_yaml(node["lifespan"], "lifespan"),
            liveliness_lease_duration=_duration_from_yaml(
                node["liveliness_lease_duration"], "liveliness_lease_duration"
            ),
            avoid_ros_namespace_conventions=bool(
                node.get("avoid_ros_namespace_conventions", False)
            ),
        )
    except KeyError as exc:
        raise QosYamlError(f"QoS profile lacks {exc.args[0]!r}: {dict(node)!r}") from exc
    except (TypeError, ValueError) as exc:
        raise QosYamlError(f"QoS profile is invalid ({exc}): {dict(node)!r}") from exc
    return profile


def _dump_sequence(items: list[dict[str, Any]]) -> str:
    lines: list[str] = []
    for item in items:
        prefix = "- "
        for key, value in item.items():
            if isinstance(value, dict):
                lines.append(f"{prefix}{key}:")
                lines.extend(f"    {k}: {v}" for k, v in value.items())
            else:
                text = str(value).lower() if isinstance(value, bool) else str(value)
                lines.append(f"{prefix}{key}: {text}")
            prefix = "  "
    return "\n".join(lines)


def qos_profiles_to_yaml(profiles: Iterable[QoSProfile]) -> str:
    """The ``offered_qos_profiles`` string rosbag2 writes for these profiles ("" for none)."""
    return _dump_sequence([qos_profile_to_dict(p) for p in profiles])


def qos_dicts_from_yaml(text: str) -> list[dict[str, Any]]:
    """Parse an ``offered_qos_profiles`` string into plain mappings ([] for "")."""
    if not text.strip():
        return []
    try:
        loaded = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise QosYamlError(f"offered_qos_profiles is not YAML: {exc}".splitlines()[0]) from exc
    if loaded is None:
        return []
    if not isinstance(loaded, list) or not all(isinstance(x, dict) for x in loaded):
        raise QosYamlError(f"offered_qos_profiles is not a list of mappings: {text[:80]!r}")
    return loaded


def qos_profiles_from_yaml(text: str) -> list[QoSProfile]:
    """Parse an ``offered_qos_profiles`` string (rosbag2 v8 or v9) into rclpy profiles.

    Raises:
        QosYamlError: the text is not a list of rosbag2 QoS mappings.
    """
    return [qos_profile_from_dict(node) for node in qos_dicts_from_yaml(text)]


def qos_profiles_text(value: str | Sequence[Mapping[str, Any]] | None) -> str:
    """Normalise metadata.yaml's ``offered_qos_profiles`` (v9 list, v8 string) to a string."""
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    return _dump_sequence([dict(v) for v in value])
