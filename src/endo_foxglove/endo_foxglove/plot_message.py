"""Any ROS message as plot-friendly JSON (for the scale topic, whatever its type).

The scale topic's message type is whatever the scale estimator publishes
(a ``std_msgs/Float64``, a ``geometry_msgs/Vector3Stamped`` with the scale
and its confidence, ...). The bridge finds the type when the topic appears
and sends each message as JSON: the message's own fields (nested messages as
objects, ``builtin_interfaces/Time`` as Foxglove's ``{sec, nsec}``, arrays as
lists, NaN/inf as null), plus one top-level number ``scale`` so that a plot
of ``/endoscope/scale.scale`` works for any type.

``scale`` is read from the ``field`` path given (``vector.x``, ``data[0]``)
or, with an empty path, from the first of: a field named ``scale`` at any
depth, ``data``, ``x``, the first numeric field.
"""

from __future__ import annotations

import array
import math
import re
from collections.abc import Iterator
from typing import Any

import numpy as np

from endo_io.errors import Endo3dError

_INDEXED = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)\])?$")
_PREFERRED = ("data", "x")


class PlotFieldError(Endo3dError, ValueError):
    """The scale field path names nothing numeric in the message."""


def _is_message(value: Any) -> bool:
    return hasattr(type(value), "get_fields_and_field_types")


def _is_time(value: Any) -> bool:
    cls = type(value)
    return cls.__module__.startswith("builtin_interfaces.msg") and cls.__name__ in (
        "Time", "Duration"
    )


def _number(value: float | int | bool) -> float | int | bool | None:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def to_json(value: Any) -> Any:
    """A ROS message (or field value) as JSON-ready Python values.

    Nested messages become dicts in field order, ``Time``/``Duration``
    ``{"sec", "nsec"}``, sequences lists, bytes lists of ints, numpy scalars
    Python numbers, non-finite floats None.
    """
    if _is_time(value):
        return {"sec": int(value.sec), "nsec": int(value.nanosec)}
    if _is_message(value):
        return {name: to_json(getattr(value, name)) for name in value.get_fields_and_field_types()}
    if isinstance(value, np.ndarray | array.array | list | tuple):
        return [to_json(v) for v in (value.tolist() if hasattr(value, "tolist") else value)]
    if isinstance(value, bytes | bytearray):
        return list(value)
    if isinstance(value, np.generic):
        return _number(value.item())
    if isinstance(value, bool | int | float):
        return _number(value)
    return str(value)


def json_schema(value: Any, title: str | None = None) -> dict[str, Any]:
    """JSON schema of :func:`to_json` of ``value`` (an instance, e.g. the type's default)."""
    data = to_json(value)

    def schema(item: Any) -> dict[str, Any]:
        if isinstance(item, dict):
            return {"type": "object", "properties": {k: schema(v) for k, v in item.items()}}
        if isinstance(item, list):
            return {"type": "array", "items": schema(item[0]) if item else {}}
        if isinstance(item, bool):
            return {"type": "boolean"}
        if isinstance(item, int):
            return {"type": "integer"}
        if isinstance(item, float) or item is None:
            return {"type": ["number", "null"]}
        return {"type": "string"}

    result = schema(data)
    result["properties"]["scale"] = {"type": ["number", "null"]}
    if title:
        result["title"] = title
    return result


def _numeric_leaves(data: Any, path: str = "") -> Iterator[tuple[str, float]]:
    if isinstance(data, dict):
        for key, item in data.items():
            yield from _numeric_leaves(item, f"{path}.{key}" if path else key)
    elif isinstance(data, list):
        for index, item in enumerate(data):
            yield from _numeric_leaves(item, f"{path}[{index}]")
    elif isinstance(data, int | float) and not isinstance(data, bool):
        yield path, float(data)


def _lookup(data: Any, path: str) -> Any:
    for part in path.split("."):
        match = _INDEXED.match(part)
        if match is None or not isinstance(data, dict) or match.group(1) not in data:
            raise PlotFieldError(f"scale field {path!r}: no {part!r} in the message")
        data = data[match.group(1)]
        if match.group(2) is not None:
            index = int(match.group(2))
            if not isinstance(data, list) or index >= len(data):
                raise PlotFieldError(f"scale field {path!r}: {part!r} is out of range")
            data = data[index]
    return data


def scale_value(data: dict[str, Any], field: str = "") -> float | None:
    """The scale in :func:`to_json` output ``data``: the ``field`` path, or the first match.

    Returns None when the chosen value is null (NaN in the message) or,
    with no path given, when the message has no numeric field at all.

    Raises:
        PlotFieldError: ``field`` is given and names nothing numeric.
    """
    if field:
        value = _lookup(data, field)
        if value is not None and (not isinstance(value, int | float) or isinstance(value, bool)):
            raise PlotFieldError(f"scale field {field!r} is not a number")
        return None if value is None else float(value)
    leaves = list(_numeric_leaves(data))
    names = [(path.rsplit(".", 1)[-1].split("[")[0], value) for path, value in leaves]
    for wanted in ("scale", *_PREFERRED):
        for name, value in names:
            if name == wanted:
                return value
    return leaves[0][1] if leaves else None


def plot_message(msg: Any, field: str = "") -> dict[str, Any]:
    """``msg`` as JSON with the top-level ``scale`` (see the module docstring)."""
    data = to_json(msg)
    data["scale"] = scale_value(data, field)
    return data
