"""The nodes' parameter file for an endo_sim recording, from its ground-truth YAML.

What a user measures or registers on a real rig, the simulator knows: the
tissue's Oren–Nayar roughness (the SFS node's ``roughness``) and the
tracker-to-world registration (the bridge's ``T_world_tracker``, so that
``/endoscope/pose`` lands in the frame of ``/ground_truth/camera_pose``).
The same settings ``endo-demo`` gives the live graph
(``endo_bringup.demo.graph_settings_for``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from endo_process.settings import BRIDGE_NODE, SFS_NODE
from endo_sim.ground_truth import ground_truth_of


def simulated_parameters(bag: Path, **sfs: Any) -> dict[str, Any]:
    """The parameter-file document (``node: {ros__parameters: ...}``) for ``bag``.

    ``sfs`` adds or overrides SFS node parameters (e.g. ``solve_scale=0.5``).
    """
    truth: dict[str, Any] = ground_truth_of(Path(bag))
    T_tracker_world = np.asarray(truth["tracker"]["T_tracker_world"], dtype=np.float64)
    roughness = float(truth["photometry"]["roughness_rad"])
    return {
        SFS_NODE: {"ros__parameters": {"roughness": roughness, **sfs}},
        BRIDGE_NODE: {
            "ros__parameters": {
                "T_world_tracker": [float(v) for v in np.linalg.inv(T_tracker_world).ravel()]
            }
        },
    }


def write_simulated_parameters(bag: Path, path: Path, **sfs: Any) -> Path:
    """Write :func:`simulated_parameters` of ``bag`` to ``path`` (YAML); returns ``path``."""
    Path(path).write_text(yaml.safe_dump(simulated_parameters(bag, **sfs), sort_keys=False))
    return Path(path)
