"""Endoscope simulator with physically based photometry, tracker simulation and ground truth.

>>> sequence = build_sequence(SimulationConfig(scene="colon"))
>>> write_bag(sequence, "colon.mcap")

The names below are imported on first use, so ``import endo_sim`` is cheap.
"""

from typing import TYPE_CHECKING

from endo_io.kernel_cache import use_kernel_cache
from endo_io.lazy_exports import lazy_exports

use_kernel_cache()  # before any kernel module is imported: see endo_io.kernel_cache

if TYPE_CHECKING:
    from endo_sim.bagout import write_bag, write_ground_truth
    from endo_sim.errors import SimulatorError
    from endo_sim.node import SimulatorNode
    from endo_sim.photometry import Photometry
    from endo_sim.render import RenderedFrame, Renderer
    from endo_sim.response import CameraResponse
    from endo_sim.sequences import Sequence, SimulationConfig, build_sequence
    from endo_sim.tracker import TrackerModel, simulate_tracker

__all__ = [
    "CameraResponse",
    "Photometry",
    "RenderedFrame",
    "Renderer",
    "Sequence",
    "SimulationConfig",
    "SimulatorError",
    "SimulatorNode",
    "TrackerModel",
    "build_sequence",
    "simulate_tracker",
    "write_bag",
    "write_ground_truth",
]
__getattr__, __dir__ = lazy_exports(__name__)
