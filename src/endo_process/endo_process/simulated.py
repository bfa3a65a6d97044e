"""The nodes' parameter file for an endo_sim recording, from its ground-truth YAML.

What a user measures or registers on a real rig, the simulator knows: the
tissue's Oren–Nayar roughness (the SFS node's ``roughness``) and the
tracker-to-world registration (the bridge's ``T_world_tracker``, so that
``/endoscope/pose`` lands in the frame of ``/ground_truth/camera_pose``) and
the unit of ``/tracker/pose`` (the bridge's ``ros_unit``: ``endo-sim render
--tracker-units mm`` records millimetres).
The same settings ``endo-demo`` gives the live graph
(``endo_bringup.demo.graph_settings_for``).

``python -m endo_process.simulated BAG -o sim.yaml`` writes the file, for
``endo-process --params sim.yaml`` on a simulated recording.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from endo_process.settings import BRIDGE_NODE, SFS_NODE
from endo_sim.errors import GroundTruthError
from endo_sim.ground_truth import ground_truth_of

# A registration further than this from the simulator's puts the outputs in
# another frame than the ground truth (pose and cloud errors then compare
# different frames). Far above what a registration is meant to differ by.
REGISTRATION_TOLERANCE_M = 1e-3
REGISTRATION_TOLERANCE_RAD = np.deg2rad(0.1)
# Without the ground-truth file there is no registration to compare with; a
# median camera pose error above this (mm) then says the frames differ: a
# wrong registration costs metres or tens of degrees, the tracker's own
# error is below a millimetre (docs/process.md).
UNCHECKED_POSE_ERROR_MM = 50.0


def simulated_parameters(bag: Path, **sfs: Any) -> dict[str, Any]:
    """The parameter-file document (``node: {ros__parameters: ...}``) for ``bag``.

    ``sfs`` adds or overrides SFS node parameters (e.g. ``solve_scale=0.5``).
    """
    truth: dict[str, Any] = ground_truth_of(Path(bag))
    T_tracker_world = np.asarray(truth["tracker"]["T_tracker_world"], dtype=np.float64)
    roughness = float(truth["photometry"]["roughness_rad"])
    # endo_sim's ground truth names the unit of /tracker/pose (absent before it did: metres)
    unit = str(truth["tracker"].get("units", "m"))
    return {
        SFS_NODE: {"ros__parameters": {"roughness": roughness, **sfs}},
        BRIDGE_NODE: {
            "ros__parameters": {
                "ros_unit": unit,
                "T_world_tracker": [float(v) for v in np.linalg.inv(T_tracker_world).ravel()],
            }
        },
    }


def write_simulated_parameters(bag: Path, path: Path, **sfs: Any) -> Path:
    """Write :func:`simulated_parameters` of ``bag`` to ``path`` (YAML); returns ``path``."""
    Path(path).write_text(yaml.safe_dump(simulated_parameters(bag, **sfs), sort_keys=False))
    return Path(path)


def registration_mismatch(
    bag: Path, T_world_tracker: np.ndarray, pose_error_mm: float | None = None
) -> str | None:
    """Why ``T_world_tracker`` does not put ``bag``'s outputs in its ground truth's frame.

    Returns None when ``T_world_tracker`` (4, 4) is the simulator's
    registration to within 1 mm / 0.1°; otherwise one sentence naming the
    truth file and the gap. A bag without endo_sim's ground-truth file
    beside it (a re-recording of a simulated bag: its ground-truth topics
    came along, the file did not) cannot be checked: then ``pose_error_mm``,
    the run's median camera pose error against those topics, decides
    (above :data:`UNCHECKED_POSE_ERROR_MM` the sentence says so); None when
    it is not given or small.
    """
    try:
        truth: dict[str, Any] = ground_truth_of(Path(bag))
        T_tracker_world = np.asarray(truth["tracker"]["T_tracker_world"], dtype=np.float64)
    except (GroundTruthError, KeyError, TypeError):
        if pose_error_mm is None or not pose_error_mm > UNCHECKED_POSE_ERROR_MM:
            return None
        return (
            f"camera pose error median {pose_error_mm:.0f} mm against the ground truth in "
            f"{Path(bag).name}: this run's world (tracker_bridge T_world_tracker) is not the "
            "simulator's, so pose and cloud errors compare different frames; no "
            f"{Path(bag).stem}.ground_truth.yaml beside it to check: run "
            "`python -m endo_process.simulated BAG -o sim.yaml` on the bag endo-sim rendered "
            "and pass --params sim.yaml"
        )
    gap = np.asarray(T_world_tracker, np.float64) @ T_tracker_world
    distance = float(np.linalg.norm(gap[:3, 3]))
    angle = float(np.arccos(np.clip((np.trace(gap[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    if distance <= REGISTRATION_TOLERANCE_M and angle <= REGISTRATION_TOLERANCE_RAD:
        return None
    return (
        f"the ground truth beside {Path(bag).name} is in the simulator's world, "
        f"{distance * 1e3:.0f} mm / {np.rad2deg(angle):.0f}° from this run's world "
        "(tracker_bridge T_world_tracker): pose and cloud errors compare different frames; "
        f"`python -m endo_process.simulated {shlex.quote(str(bag))} -o sim.yaml` writes the "
        "simulator's registration, tracker unit and roughness, then pass --params sim.yaml"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m endo_process.simulated BAG -o PARAMS.yaml``."""
    parser = argparse.ArgumentParser(
        prog="python -m endo_process.simulated",
        description="Write the nodes' parameter file (tracker registration, tissue roughness) "
        "that puts an endo_sim recording's outputs in its ground truth's frame.",
    )
    parser.add_argument("bag", type=Path, help="a bag written by endo-sim render")
    parser.add_argument("-o", "--output", type=Path, required=True, help="parameter YAML")
    args = parser.parse_args(argv)
    try:
        write_simulated_parameters(args.bag, args.output)
    except GroundTruthError as error:
        print(f"{parser.prog}: {error}", file=sys.stderr)
        return 2
    print(f"{parser.prog}: wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
