"""The tissue texture's amplitudes: options, the CLI flags and the ground truth record."""

from __future__ import annotations

import numpy as np
import pytest

from endo_sim.cli import build_parser, config_from_args
from endo_sim.errors import SimulationParameterError
from endo_sim.texture import MUCOSA_GREY, TextureOptions, tissue_texture


def _contrast(options: TextureOptions) -> float:
    grey = tissue_texture(4, (0.04, 0.03), options=options).albedo[..., 0]
    return float(np.std(grey) / np.mean(grey))


def test_amplitudes_scale_the_contrast_and_zero_is_a_uniform_albedo() -> None:
    flat = tissue_texture(4, (0.04, 0.03), options=TextureOptions(0.0, 0.0, 0.0)).albedo
    np.testing.assert_allclose(flat, MUCOSA_GREY, rtol=1e-6)
    default = _contrast(TextureOptions())
    smooth = _contrast(TextureOptions(drift=0.02))
    no_vessels = _contrast(TextureOptions(vessel_density_per_cm2=0.0))
    assert smooth < default and no_vessels < default
    # the slow drift alone: its ln amplitude is the contrast (unit-variance noise)
    drift_only = _contrast(TextureOptions(drift=0.08, mottle=0.0, vessel_density_per_cm2=0.0))
    assert drift_only == pytest.approx(0.08, rel=0.1)
    # the same seed draws the same fields whatever the amplitudes
    a = tissue_texture(4, (0.04, 0.03), options=TextureOptions(0.08, 0.0, 0.0)).albedo
    b = tissue_texture(4, (0.04, 0.03), options=TextureOptions(0.04, 0.0, 0.0)).albedo
    np.testing.assert_allclose(np.log(b / MUCOSA_GREY), 0.5 * np.log(a / MUCOSA_GREY),
                               atol=1e-5)
    with pytest.raises(SimulationParameterError):
        TextureOptions(drift=-0.1)


def test_cli_flags_reach_the_configuration() -> None:
    args = build_parser().parse_args(
        ["render", "abdomen", "-o", "x.mcap", "--specular", "0", "--albedo-drift", "0.02",
         "--albedo-mottle", "0.03", "--vessel-density", "0"])
    config = config_from_args(args)
    assert config.texture == TextureOptions(drift=0.02, mottle=0.03, vessel_density_per_cm2=0.0)
    assert config.photometry.specular_strength == 0.0
    default = config_from_args(build_parser().parse_args(["render", "abdomen", "-o", "x.mcap"]))
    assert default.texture == TextureOptions()
