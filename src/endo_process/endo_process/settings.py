"""The nodes' parameters, for an offline run: the live defaults, a ROS 2 parameter file over them.

``endo-process --params endo3d.yaml`` reads the same file a launch passes
to the nodes (``ros2 run ... --ros-args --params-file endo3d.yaml``)::

    photometric_correction:
      ros__parameters: {channel: luminance}
    sfs:
      ros__parameters: {model: near_light, roughness: 0.3, solve_scale: 0.5}
    tracker_bridge:
      ros__parameters:
        T_world_tracker: [1.0, 0.0, 0.0, 0.0,  0.0, 1.0, 0.0, 0.0,
                          0.0, 0.0, 1.0, 0.0,  0.0, 0.0, 0.0, 1.0]
    flow:
      ros__parameters: {...}

A section applies to the nodes rcl would give it in the root namespace
(``endo_io.parameters.section_applies``: ``sfs``, ``/sfs``, ``/**/sfs``;
``/**`` to every node), in the file's order. Each node's defaults are the live
node's own (``endo_sfs.node.PARAMETERS`` for the SFS node), so a run
without a file processes exactly what the nodes started without parameters
would. Names a node does not have are refused, with the node and the name
(in a section for several nodes, such as ``/**``, they are another node's and
skipped). A section that applies to none of the nodes (another namespace's
``/rig1/sfs``, a camera driver's) is listed in
:attr:`ProcessSettings.ignored_sections`; one whose node name is a near
miss of a node's (``sfss``) is refused.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from endo_calib.node import PARAMETERS as CORRECTION_PARAMETERS
from endo_flow.node import PARAMETERS as FLOW_PARAMETERS
from endo_io.errors import ParameterValidationError, yaml_error_line
from endo_io.parameters import is_near_miss, section_applies, sections_for_no_node
from endo_process.errors import ParameterFileError
from endo_sfs.errors import SfsError
from endo_sfs.node import PARAMETERS as SFS_PARAMETERS
from endo_sfs.options import SfsOptions
from endo_tracker_bridge.conventions import LengthUnit
from endo_tracker_bridge.errors import TrackerSourceError
from endo_tracker_bridge.node import PARAMETERS as BRIDGE_PARAMETERS
from endo_tracker_bridge.node import world_tracker_from_parameter
from endo_tracker_bridge.validation import SpeedLimits

#: Node names of the live graph whose parameters the offline run takes.
CORRECTION_NODE = "photometric_correction"
SFS_NODE = "sfs"
BRIDGE_NODE = "tracker_bridge"
FLOW_NODE = "flow"

#: The correction node's parameters (``endo_calib.node.PARAMETERS``) and their
#: defaults; ``channel``, ``mask_extrapolated`` and ``output_encoding`` change the result.
CORRECTION_DEFAULTS: dict[str, Any] = {spec.name: spec.default for spec in CORRECTION_PARAMETERS}
#: The bridge's parameters that apply to a recorded ``ros`` source
#: (``endo_tracker_bridge.node``; the others choose and open a live source).
BRIDGE_DEFAULTS: dict[str, Any] = {
    spec.name: spec.default
    for spec in BRIDGE_PARAMETERS
    if spec.name in (
        "source", "handeye_file", "T_world_tracker", "world_frame", "tracker_frame",
        "max_speed_m_s", "max_angular_speed_deg_s", "rotation_tolerance", "ros_topic",
        "ros_unit", "ros_frame_id", "tool_id",
    )
}
#: The SFS node's parameters that are :class:`SfsOptions` fields of the same name
#: (the node builds its options from exactly these).
SFS_DEFAULTS: dict[str, Any] = {spec.name: spec.default for spec in SFS_PARAMETERS}
#: The flow node's parameters (``endo_flow.node.PARAMETERS``) and their defaults.
FLOW_DEFAULTS: dict[str, Any] = {spec.name: spec.default for spec in FLOW_PARAMETERS}
#: Parameters of the live nodes that do not change an offline result
#: (diagnostics, live sources, frame skipping): accepted in a file and ignored,
#: so that the file the nodes get (config/endo3d.yaml) serves endo-process too.
LIVE_ONLY: dict[str, frozenset[str]] = {
    CORRECTION_NODE: frozenset(s.name for s in CORRECTION_PARAMETERS) - set(CORRECTION_DEFAULTS),
    BRIDGE_NODE: frozenset(s.name for s in BRIDGE_PARAMETERS) - set(BRIDGE_DEFAULTS),
}
#: Every parameter name of the four nodes, live-only ones too.
ALL_NAMES = frozenset(
    spec.name
    for table in (CORRECTION_PARAMETERS, SFS_PARAMETERS, BRIDGE_PARAMETERS, FLOW_PARAMETERS)
    for spec in table
)
SFS_OPTION_PARAMETERS = tuple(
    f.name for f in dataclasses.fields(SfsOptions) if f.name in SFS_DEFAULTS
)


#: The offline run's nodes, in the root namespace.
NODES = (CORRECTION_NODE, SFS_NODE, BRIDGE_NODE, FLOW_NODE)


@dataclass(frozen=True)
class ParameterSection:
    """One section of a parameter file.

    Attributes:
        key: the section's key (``/**/sfs``).
        nodes: the offline run's nodes it applies to (:data:`NODES`' names).
        parameters: its ``ros__parameters`` mapping.
    """

    key: str
    nodes: tuple[str, ...]
    parameters: dict[str, Any]


def read_parameter_file(path: Path) -> list[ParameterSection]:
    """The sections of a ROS 2 parameter file, in its order.

    Raises:
        ParameterFileError: unreadable file, not YAML, not the
            ``node: {ros__parameters: {...}}`` layout, or a section whose
            node name is a near miss of a node's (``sfss``).
    """
    try:
        document = yaml.safe_load(Path(path).read_text())
    except OSError as error:
        raise ParameterFileError(f"{path}: cannot read ({error.strerror})") from None
    except yaml.YAMLError as error:
        raise ParameterFileError(f"{path}: not YAML ({yaml_error_line(error)})") from None
    if document is None:
        return []
    if not isinstance(document, Mapping):
        raise ParameterFileError(f"{path}: expected a mapping of node names")
    sections = []
    for name, section in document.items():
        parameters = section.get("ros__parameters") if isinstance(section, Mapping) else None
        if not isinstance(parameters, Mapping):
            raise ParameterFileError(f"{path}: node {name!r} has no ros__parameters mapping")
        nodes = tuple(node for node in NODES if section_applies(name, f"/{node}"))
        sections.append(ParameterSection(str(name), nodes, dict(parameters)))
    try:
        sections_for_no_node(document, [f"/{node}" for node in NODES])
    except ParameterValidationError as error:
        raise ParameterFileError(f"{path}: {error}") from None
    return sections


def _node_values(
    sections: Sequence[ParameterSection], node: str, defaults: Mapping[str, Any], path: str
) -> dict[str, Any]:
    """The node's defaults with the file's sections for it over them, in the file's order."""
    values = dict(defaults)
    for section in sections:
        if node not in section.nodes:
            continue
        for name, value in section.parameters.items():
            if name not in defaults:
                if name in LIVE_ONLY.get(node, ()):
                    continue  # a live node's that changes nothing offline
                if len(section.nodes) > 1 and name in ALL_NAMES:
                    continue  # another node's, in a section for several (`/**`)
                close = [row for row in defaults if is_near_miss(name, row)]
                if len(section.nodes) > 1 and not close:
                    continue  # rcl gives it to every node; the node ignores it (with a word)
                hint = f" (did you mean {close[0]}?)" if close else ""
                raise ParameterFileError(
                    f"{path}: node {node!r} has no parameter {name!r}{hint}")
            default = defaults[name]
            if isinstance(default, bool) != isinstance(value, bool) or (
                isinstance(default, int | float) and not isinstance(value, int | float)
            ):
                raise ParameterFileError(
                    f"{path}: {node}.{name} must be like {default!r}, got {value!r}"
                )
            values[name] = float(value) if isinstance(default, float) else value
    return values


@dataclass(frozen=True)
class ProcessSettings:
    """Everything the cores take besides the calibrations, from the nodes' parameters.

    Attributes:
        channel: the correction node's ``channel``.
        mask_extrapolated: the correction node's ``mask_extrapolated`` (NaN
            above the calibration's observed range).
        output_encoding: the correction node's ``output_encoding`` (16UC1
            fixed point or 32FC1), of image_corrected and of what is solved.
        sfs: the SFS node's parameters (name -> value), every one of them.
        bridge: the tracker bridge's parameters for a ``ros`` source.
        flow: the flow node's parameters, every one of them.
        ignored_sections: the parameter file's sections that apply to none
            of the nodes (their keys), ignored.
    """

    channel: str = "luminance"
    mask_extrapolated: bool = False
    output_encoding: str = "16UC1"
    sfs: dict[str, Any] = field(
        default_factory=lambda: dict(SFS_DEFAULTS)
    )
    bridge: dict[str, Any] = field(default_factory=lambda: dict(BRIDGE_DEFAULTS))
    flow: dict[str, Any] = field(default_factory=lambda: dict(FLOW_DEFAULTS))
    ignored_sections: tuple[str, ...] = ()

    @property
    def sfs_options(self) -> SfsOptions:
        """The solver settings the SFS node builds from these parameters."""
        return SfsOptions(**{name: self.sfs[name] for name in SFS_OPTION_PARAMETERS})

    @property
    def T_world_tracker(self) -> np.ndarray:
        """(4, 4) float64 tracker → world, checked as the bridge checks it."""
        return world_tracker_from_parameter(self.bridge["T_world_tracker"])

    @property
    def speed_limits(self) -> SpeedLimits:
        """The bridge's gate limits."""
        return SpeedLimits(
            float(self.bridge["max_speed_m_s"]), float(self.bridge["max_angular_speed_deg_s"])
        )

    @property
    def tracker_unit(self) -> LengthUnit:
        """Unit of the recorded driver poses (the bridge's ``ros_unit``)."""
        return LengthUnit.parse(str(self.bridge["ros_unit"]))


def load_settings(path: Path | None, *, solve_scale: float | None = None) -> ProcessSettings:
    """The nodes' defaults, with ``path``'s values and then ``solve_scale`` over them.

    Raises:
        ParameterFileError: the file cannot be read, names a parameter a
            node does not have, gives a value of the wrong kind, or holds a
            T_world_tracker / ros_unit the bridge would refuse.
    """
    nodes = read_parameter_file(path) if path is not None else []
    where = str(path) if path is not None else "the nodes' defaults"
    correction = _node_values(nodes, CORRECTION_NODE, CORRECTION_DEFAULTS, where)
    settings = ProcessSettings(
        channel=str(correction["channel"]),
        mask_extrapolated=bool(correction["mask_extrapolated"]),
        output_encoding=str(correction["output_encoding"]),
        sfs=_node_values(nodes, SFS_NODE, SFS_DEFAULTS, where),
        bridge=_node_values(nodes, BRIDGE_NODE, BRIDGE_DEFAULTS, where),
        flow=_node_values(nodes, FLOW_NODE, FLOW_DEFAULTS, where),
        ignored_sections=tuple(section.key for section in nodes if not section.nodes),
    )
    if solve_scale is not None:
        settings.sfs["solve_scale"] = float(solve_scale)
    try:
        settings.T_world_tracker  # noqa: B018 - validated once, here
        settings.tracker_unit  # noqa: B018
    except TrackerSourceError as error:
        raise ParameterFileError(f"{where}: {BRIDGE_NODE}: {error}") from None
    try:
        settings.sfs_options  # noqa: B018
    except SfsError as error:
        given = f" with --solve-scale {solve_scale:g}" if solve_scale is not None else ""
        raise ParameterFileError(f"{where}{given}: {SFS_NODE}: {error}") from None
    return settings
