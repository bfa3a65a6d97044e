"""A node's parameters declared from one table, validated at start-up and at run time.

Each node lists its parameters as :class:`ParameterSpec` rows (name,
default, description, range or choices, read-only or not) and hands them to
:class:`NodeParameters`, which

* declares every row with a full ``ParameterDescriptor`` (type, description,
  range, ``additional_constraints`` naming the choices, read-only), so that
  ``ros2 param describe`` and ``--help`` show them;
* validates the values the node starts with: a wrong type, a value out of
  range or outside its choices raises :class:`ParameterValidationError` with
  one line naming the parameter, which :func:`endo_io.process.run_node`
  prints before exiting with code 2;
* refuses a start-up override whose name is an edit or two away from a
  row (``solve_scal`` for ``solve_scale``): a typo in a parameter file would
  otherwise be ignored in silence and the node run on its default; any other
  name that is not the node's is logged once as ignored (a ``/**`` section
  shared by every node legitimately carries other nodes' parameters);
* accepts an integer for a double (``-p solve_scale:=1``, as users type
  it; rclpy alone refuses it for a double-typed parameter) and a number for
  a string (``-p tool_id:=7``);
* validates every run-time change the same way and then hands the accepted
  values to the node's ``apply`` callback, which puts them into effect or
  refuses them by raising an :class:`endo_io.errors.Endo3dError`; its
  message is the reason the caller gets. Read-only rows are refused by rclpy
  itself.

How an integer gets into a double parameter: rclpy fixes a parameter's
type at declaration and refuses an override of another type with a
traceback. Each row is therefore first declared dynamically typed (any
override is taken as it is), read and converted, then undeclared and
declared again, statically typed, with the converted value. At run time a
pre-set callback converts integers for doubles before rclpy checks types.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from endo_io.errors import Endo3dError, ParameterValidationError

Type = Parameter.Type

_NUMBER_TYPES = (Type.INTEGER, Type.DOUBLE, Type.INTEGER_ARRAY, Type.DOUBLE_ARRAY)
_ARRAY_ELEMENT = {
    Type.BOOL_ARRAY: Type.BOOL,
    Type.INTEGER_ARRAY: Type.INTEGER,
    Type.DOUBLE_ARRAY: Type.DOUBLE,
    Type.STRING_ARRAY: Type.STRING,
}
# Overrides rclpy itself reads when a publisher or subscription is made.
_RCLPY_PREFIXES = ("qos_overrides.",)
_TYPE_WORDS = {
    Type.BOOL: "true or false",
    Type.INTEGER: "an integer",
    Type.DOUBLE: "a number",
    Type.STRING: "a string",
}


def _edit_distance(a: str, b: str) -> int:
    """Edits (insert, delete, substitute, swap two neighbours) turning ``a`` into ``b``."""
    previous2: list[int] = []
    previous = list(range(len(b) + 1))
    for i, char_a in enumerate(a, 1):
        current = [i]
        for j, char_b in enumerate(b, 1):
            cost = min(previous[j] + 1, current[j - 1] + 1, previous[j - 1] + (char_a != char_b))
            if i > 1 and j > 1 and char_a == b[j - 2] and a[i - 2] == char_b:
                cost = min(cost, previous2[j - 2] + 1)
            current.append(cost)
        previous2, previous = previous, current
    return previous[-1]


def is_near_miss(name: str, row: str) -> bool:
    """Whether ``name`` is a typo of ``row``: one edit away, two for names of 8+ letters."""
    return 0 < _edit_distance(name, row) <= (2 if len(row) >= 8 else 1)


@dataclass(frozen=True)
class ParameterSpec:
    """One row of a node's parameter table.

    Attributes:
        name: the parameter's name.
        default: its default value; its type is the parameter's type unless
            ``type`` says otherwise (needed for an empty list).
        description: what it does, with its unit.
        range: inclusive (low, high) of a number, or of every element of a
            number array; None for no range.
        choices: the allowed values of a string (or of every element of a
            string array); None for any.
        read_only: fixed at start-up; rclpy refuses run-time changes.
        type: the rclpy parameter type; None infers it from ``default``.
    """

    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] | None = None
    read_only: bool = False
    type: Type | None = None

    def __post_init__(self) -> None:
        if self.range is not None and self.parameter_type not in _NUMBER_TYPES:
            raise ValueError(f"{self.name}: a range needs a number parameter")
        if self.choices is not None and self.parameter_type not in (
            Type.STRING, Type.STRING_ARRAY
        ):
            raise ValueError(f"{self.name}: choices need a string parameter")
        self.validate(self.default)  # a table whose defaults fail is a programming error

    @property
    def parameter_type(self) -> Type:
        """The parameter's rclpy type."""
        if self.type is not None:
            return self.type
        return Type.from_parameter_value(self.default)

    @property
    def constraints(self) -> str:
        """The range or choices in words ('' when neither), as ``--help`` shows them."""
        if self.choices is not None:
            return "one of: " + ", ".join(self.choices)
        if self.range is not None:
            low, high = self.range
            return f"in [{low:g}, {high:g}]"
        return ""

    def descriptor(self) -> ParameterDescriptor:
        """The ``ParameterDescriptor`` rclpy declares the parameter with."""
        descriptor = ParameterDescriptor(
            name=self.name,
            type=self.parameter_type.value,
            description=self.description,
            additional_constraints=self.constraints,
            read_only=self.read_only,
        )
        if self.range is not None:
            low, high = self.range
            if self.parameter_type in (Type.INTEGER, Type.INTEGER_ARRAY):
                descriptor.integer_range = [
                    IntegerRange(from_value=int(low), to_value=int(high), step=1)
                ]
            else:
                descriptor.floating_point_range = [
                    FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)
                ]
        return descriptor

    def validate(self, value: Any) -> Any:
        """The value converted to this parameter's type, checked against range and choices.

        Args:
            value: what rclpy holds (from ``-p``, a YAML file or a set request).

        Returns:
            bool, int, float or str, or a list of them for an array parameter.

        Raises:
            ParameterValidationError: wrong type, out of range, not a choice; the
                message is one line naming the parameter.
        """
        kind = self.parameter_type
        element = _ARRAY_ELEMENT.get(kind)
        if element is None:
            return self._check(self._convert(value, kind, value), value)
        if isinstance(value, str | bytes) or not isinstance(value, Iterable):
            raise ParameterValidationError(
                f"parameter {self.name}: expected a list, got {value!r}"
            )
        items = [self._convert(item, element, value) for item in value]
        return [self._check(item, value) for item in items]

    def _convert(self, value: Any, kind: Type, given: Any) -> Any:
        if kind == Type.BOOL and isinstance(value, bool):
            return value
        if not isinstance(value, bool):
            if kind == Type.INTEGER and isinstance(value, int):
                return int(value)
            if kind == Type.DOUBLE and isinstance(value, int | float):
                return float(value)
            if kind == Type.STRING and isinstance(value, str):
                return value
            if kind == Type.STRING and isinstance(value, int | float):
                return str(value)  # `-p tool_id:=7` arrives as an integer
        raise ParameterValidationError(
            f"parameter {self.name}: expected {_TYPE_WORDS[kind]}, got {given!r}"
        )

    def _check(self, value: Any, given: Any) -> Any:
        if self.range is not None:
            low, high = self.range
            if not low <= value <= high:  # NaN too
                raise ParameterValidationError(
                    f"parameter {self.name}: {given!r} is out of range [{low:g}, {high:g}]"
                )
        if self.choices is not None and value not in self.choices:
            raise ParameterValidationError(
                f"parameter {self.name}: {given!r} is not one of {', '.join(self.choices)}"
            )
        return value


#: Parameters rclpy declares on every node itself, besides a node's table.
ROS_OWN_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service"})


def refuse_near_misses(
    names: Iterable[str], specs: Mapping[str, ParameterSpec], node_name: str
) -> None:
    """Refuse a start-up override whose name is a typo of a row (``solve_scal``).

    Args:
        names: overrides given that are none of the rows.
        specs: the node's table by name.
        node_name: the node, for the message.

    Raises:
        ParameterValidationError: a name is a near miss (:func:`is_near_miss`)
            of a row's: ``parameter solve_scal: sfs has no such parameter (did
            you mean solve_scale?)``.
    """
    for name in names:
        close = [row for row in specs if is_near_miss(name, row)]
        if close:
            raise ParameterValidationError(
                f"parameter {name}: {node_name} has no such parameter (did you mean {close[0]}?)"
            )


def check_start_values(
    specs: Sequence[ParameterSpec], given: Mapping[str, Any], node_name: str
) -> dict[str, Any]:
    """The values a node will start with, checked as :class:`NodeParameters` checks them.

    For a launcher that checks a node's configuration before starting it
    (``endo-launch``): each row's override or default through
    :meth:`ParameterSpec.validate`, then :func:`refuse_near_misses`, in the
    node's order, without creating a node.

    Args:
        specs: the node's table.
        given: the start-up overrides (parameter file and ``-p``), name ->
            value as parsed from YAML.
        node_name: the node, for the message.

    Returns:
        Every row's value, converted.

    Raises:
        ParameterValidationError: the first value the node would refuse.
    """
    rows = {spec.name: spec for spec in specs}
    values = {spec.name: spec.validate(given.get(spec.name, spec.default)) for spec in specs}
    refuse_near_misses(
        sorted(name for name in given if name not in rows and name not in ROS_OWN_PARAMETERS
               and not name.startswith(_RCLPY_PREFIXES)),
        rows, node_name,
    )  # fmt: skip
    return values


def _flatten(prefix: str, values: Mapping[Any, Any], into: dict[str, Any]) -> None:
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            _flatten(name + ".", value, into)
        else:
            into[name] = value


def section_applies(key: object, fqn: str) -> bool:
    """Whether a parameter file's section ``key`` applies to the node ``fqn``, as rcl decides.

    ``/**``, ``/**/sfs``, ``sfs``, ``/rig1/sfs``: ``*`` stands for one name,
    ``**`` for any number; a key without a leading ``/`` is from the root.

    Args:
        key: the section's key as parsed from YAML.
        fqn: the node's fully qualified name (``/sfs``, ``/rig1/sfs``).
    """
    pattern = "/" + str(key).lstrip("/")
    regex = re.escape(pattern).replace(r"/\*\*", "(/[^/]+)*").replace(r"\*", "[^/]*")
    return re.fullmatch(regex, fqn) is not None


def sections_for_no_node(document: Any, fqns: Collection[str]) -> list[str]:
    """The keys of a parameter file's sections that apply to none of the nodes ``fqns``.

    Such a section is ignored by rcl without a word: another program's (a
    camera driver's), another namespace's, or a misspelt node name.

    Args:
        document: the parsed YAML (``yaml.safe_load``).
        fqns: the fully qualified names of the nodes the file is given to.

    Returns:
        The keys (as strings), in the file's order.

    Raises:
        ParameterValidationError: a key's node name is a near miss
            (:func:`is_near_miss`) of one of the nodes' names: ``section
            /**/sfss of the parameter file applies to no node (did you mean
            sfs?)``.
    """
    if not isinstance(document, Mapping):
        return []
    names = sorted({fqn.rsplit("/", 1)[-1] for fqn in fqns})
    unmatched = []
    for key in document:
        if any(section_applies(key, fqn) for fqn in fqns):
            continue
        last = str(key).rsplit("/", 1)[-1]
        close = [name for name in names if is_near_miss(last, name)]
        if close:
            raise ParameterValidationError(
                f"section {key} of the parameter file applies to no node "
                f"(did you mean {close[0]}?)"
            )
        unmatched.append(str(key))
    return unmatched


def file_overrides(document: Any, node_name: str, namespace: str = "") -> dict[str, Any]:
    """The values a ROS 2 parameter file gives one node, as rcl applies them at start.

    Every section whose key matches the node's fully qualified name applies,
    in the file's order (a later one wins): ``/**``, ``/**/sfs``, ``sfs``,
    ``/rig1/sfs``; ``*`` stands for one name, ``**`` for any number. Nested
    mappings are dotted names (``qos_overrides./topic.reliability``).

    Args:
        document: the parsed YAML (``yaml.safe_load``), which rcl accepted.
        node_name: the node's name.
        namespace: its namespace ("" or ``/rig1``).

    Returns:
        Parameter name -> value.
    """
    fqn = f"{namespace.rstrip('/')}/{node_name}"
    values: dict[str, Any] = {}
    if not isinstance(document, Mapping):
        return values
    for key, section in document.items():
        if not section_applies(key, fqn) or not isinstance(section, Mapping):
            continue
        parameters = section.get("ros__parameters")
        if isinstance(parameters, Mapping):
            _flatten("", parameters, values)
    return values


#: A node's reaction to accepted changes: ``apply(changes, values)`` with the
#: changed parameters and every parameter's value after the change; it puts
#: them into effect, or raises an Endo3dError to refuse them (nothing changes).
ApplyCallback = Callable[[dict[str, Any], dict[str, Any]], None]


class NodeParameters:
    """The declared, validated parameters of one node (a read-only mapping of values).

    Args:
        node: the node to declare them on.
        specs: the node's table.

    Raises:
        ParameterValidationError: a start-up value (override) is invalid.
    """

    def __init__(self, node: Node, specs: Sequence[ParameterSpec]) -> None:
        self._node = node
        self.specs: dict[str, ParameterSpec] = {spec.name: spec for spec in specs}
        self._values: dict[str, Any] = {}
        for spec in specs:
            dynamic = ParameterDescriptor(dynamic_typing=True, description=spec.description)
            given = node.declare_parameter(spec.name, spec.default, dynamic).value
            value = spec.validate(given)
            node.undeclare_parameter(spec.name)
            node.declare_parameter(spec.name, value, spec.descriptor(), ignore_override=True)
            self._values[spec.name] = value
        self._check_unknown_overrides(node)
        self._apply: ApplyCallback | None = None
        node.add_pre_set_parameters_callback(self._convert_numbers)
        node.add_on_set_parameters_callback(self._on_set)

    def __getitem__(self, name: str) -> Any:
        return self._values[name]

    def _check_unknown_overrides(self, node: Node) -> None:
        """Refuse a start-up override that is a near miss of a row; log the other strangers.

        Raises:
            ParameterValidationError: an override's name is a near miss of a
                row's (:func:`is_near_miss`) but is not one.
        """
        # rclpy keeps the --ros-args / --params-file values the node was given.
        given = getattr(node, "_parameter_overrides", {})
        unknown = sorted(
            name for name in given
            if name not in self.specs
            and not node.has_parameter(name)  # use_sim_time and rclpy's own
            and not name.startswith(_RCLPY_PREFIXES)
        )
        refuse_near_misses(unknown, self.specs, node.get_name())
        if unknown:
            node.get_logger().warning(
                f"ignoring parameter(s) that {node.get_name()} does not have: "
                f"{', '.join(unknown)} (`--help` lists its parameters)"
            )

    def values(self) -> dict[str, Any]:
        """A copy of every parameter's current value."""
        return dict(self._values)

    def on_change(self, apply: ApplyCallback) -> None:
        """Hand accepted run-time changes to ``apply`` from now on (see :data:`ApplyCallback`).

        Without it, an accepted change just updates the values this mapping
        returns: a node that reads them where it uses them needs no callback.
        """
        self._apply = apply

    def _convert_numbers(self, parameters: list[Parameter]) -> list[Parameter]:
        """Integers given for double parameters become doubles before rclpy checks types."""
        converted = []
        for parameter in parameters:
            spec = self.specs.get(parameter.name)
            if spec is not None and spec.parameter_type in (Type.DOUBLE, Type.DOUBLE_ARRAY):
                # A value that does not convert is left as it is: _on_set
                # refuses it with the reason.
                with contextlib.suppress(ParameterValidationError):
                    parameter = Parameter(
                        parameter.name, spec.parameter_type, spec.validate(parameter.value)
                    )
            converted.append(parameter)
        return converted

    def _on_set(self, parameters: list[Parameter]) -> SetParametersResult:
        # Parameters not in the table (qos_overrides.*, use_sim_time) are
        # not this table's business: rclpy declares them while the node
        # builds its publishers.
        changes: dict[str, Any] = {}
        try:
            for parameter in parameters:
                spec = self.specs.get(parameter.name)
                if spec is not None:
                    changes[parameter.name] = spec.validate(parameter.value)
            if not changes:
                return SetParametersResult(successful=True)
            values = {**self._values, **changes}
            if self._apply is not None:
                self._apply(changes, values)
        except Endo3dError as error:
            return SetParametersResult(successful=False, reason=str(error))
        self._values = values
        return SetParametersResult(successful=True)
