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


def test_live_honours_duration_and_says_its_own_default(monkeypatch) -> None:
    """``endo-sim live colon --duration 3`` ran an hour-long motion: the flag was overwritten.

    Its help said "length in s, colon/abdomen (10)" while live used 3600 s whatever was given.
    """
    import endo_io.process
    import endo_sim.cli

    built: list[float] = []

    def plan(config):  # the sequence a live run would play, without rendering it
        built.append(config.duration_s)
        raise SystemExit(0)

    monkeypatch.setattr(endo_sim.cli, "build_sequence", plan)
    monkeypatch.setattr(endo_io.process, "run_node", lambda *a, **k: 0)
    for argv, duration in ((["live", "colon"], endo_sim.cli.LIVE_DURATION_S),
                           (["live", "colon", "--duration", "3"], 3.0)):  # fmt: skip
        with pytest.raises(SystemExit):
            endo_sim.cli.main(argv)
        assert built.pop() == duration
    live = next(a for a in build_parser()._subparsers._group_actions[0].choices["live"]._actions
                if "--duration" in a.option_strings)  # fmt: skip
    assert live.default == 3600.0 and "repeats after" in (live.help or "")
    assert build_parser().parse_args(["render", "colon", "-o", "x.mcap"]).duration == 10.0
