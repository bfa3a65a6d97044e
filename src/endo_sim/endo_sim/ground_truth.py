"""Reading the ground truth that ``endo-sim render`` writes beside a bag."""

from __future__ import annotations

from pathlib import Path

import yaml

from endo_sim.errors import GroundTruthError


def ground_truth_of(bag: Path) -> dict[str, object]:
    """The simulator's ``<stem>.ground_truth.yaml`` beside ``bag``, as a mapping.

    Raises:
        GroundTruthError: the file is missing or is not a mapping.
    """
    path = Path(bag).with_name(Path(bag).stem + ".ground_truth.yaml")
    if not path.exists():
        raise GroundTruthError(f"{path} not found (endo-sim writes it beside the bag)")
    loaded = yaml.safe_load(path.read_text())
    if not isinstance(loaded, dict):
        raise GroundTruthError(f"{path} is not a ground-truth mapping")
    return loaded
