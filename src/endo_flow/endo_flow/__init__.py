"""Lucas–Kanade flow and tracker poses to absolute scale, metric depth and world-frame points.

``FlowPipeline(options).process(FlowFrame(...)) -> FlowOutput`` is the per-frame
step shared by the ``endo-flow`` node and the offline processor; see
``docs/flow.md``. The names below are imported on first use.
"""

from typing import TYPE_CHECKING

from endo_io.kernel_cache import use_kernel_cache
from endo_io.lazy_exports import lazy_exports

use_kernel_cache()  # before any kernel module is imported: see endo_io.kernel_cache

if TYPE_CHECKING:
    from endo_flow.errors import FlowError, FlowInputError, NoFeaturesError
    from endo_flow.pipeline import (
        FlowDiagnostics,
        FlowFrame,
        FlowOptions,
        FlowOutput,
        FlowPipeline,
    )
    from endo_flow.scale import ScaleEstimate, ScaleState
    from endo_flow.shape_correction import ShapeCorrectionOptions
    from endo_flow.voxel_map import VoxelMap, write_ply

__all__ = [
    "FlowDiagnostics",
    "FlowError",
    "FlowFrame",
    "FlowInputError",
    "FlowOptions",
    "FlowOutput",
    "FlowPipeline",
    "NoFeaturesError",
    "ScaleEstimate",
    "ScaleState",
    "ShapeCorrectionOptions",
    "VoxelMap",
    "write_ply",
]
__getattr__, __dir__ = lazy_exports(__name__)
