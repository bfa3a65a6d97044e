"""endo_process.simulated: a simulated recording's registration, checked and written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from endo_process.settings import load_settings
from endo_process.simulated import main, registration_mismatch, simulated_parameters

BAGS = Path(__file__).resolve().parents[3] / "bags"
PHANTOM = BAGS / "phantom_colon.mcap"


def test_the_default_identity_registration_is_named_as_another_frame():
    message = registration_mismatch(PHANTOM, np.eye(4))
    assert message is not None
    assert "phantom_colon.mcap" in message and "--params sim.yaml" in message
    assert "\n" not in message


def test_the_simulators_registration_and_a_bag_without_truth_raise_nothing(tmp_path):
    document = simulated_parameters(PHANTOM)
    T_world_tracker = np.asarray(
        document["tracker_bridge"]["ros__parameters"]["T_world_tracker"]
    ).reshape(4, 4)
    assert registration_mismatch(PHANTOM, T_world_tracker) is None
    # 2 mm off is no longer the simulator's world
    shifted = T_world_tracker.copy()
    shifted[0, 3] += 2e-3
    assert "2 mm" in (registration_mismatch(PHANTOM, shifted) or "")
    assert registration_mismatch(tmp_path / "own_rig.mcap", np.eye(4)) is None


def test_the_suggested_command_quotes_a_path_with_spaces(tmp_path):
    # the warning's command is meant to be pasted into a shell as it stands
    rig = tmp_path / "rig 642"
    rig.mkdir()
    (rig / "colon16.ground_truth.yaml").write_text(
        PHANTOM.with_name("phantom_colon.ground_truth.yaml").read_text())
    message = registration_mismatch(rig / "colon16", np.eye(4)) or ""
    assert f"simulated '{rig / 'colon16'}' -o sim.yaml" in message


def test_the_written_file_loads_as_endo_process_settings(tmp_path, capsys):
    out = tmp_path / "sim.yaml"
    assert main([str(PHANTOM), "-o", str(out)]) == 0
    settings = load_settings(out)
    truth = yaml.safe_load(PHANTOM.with_name("phantom_colon.ground_truth.yaml").read_text())
    T_tracker_world = np.asarray(truth["tracker"]["T_tracker_world"], np.float64)
    np.testing.assert_allclose(settings.T_world_tracker @ T_tracker_world, np.eye(4), atol=1e-12)
    assert settings.sfs["roughness"] == truth["photometry"]["roughness_rad"]
    assert main([str(tmp_path / "none.mcap"), "-o", str(out)]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_a_millimetre_tracker_recording_gets_the_bridges_unit(tmp_path):
    # `endo-sim render --tracker-units mm` records /tracker/pose in mm and says so in its
    # truth; without ros_unit: mm every sample after the first moved "metres" per frame
    # and the speed gate rejected 239 of 240 (a 642x481 render at 120 Hz)
    assert simulated_parameters(PHANTOM)["tracker_bridge"]["ros__parameters"]["ros_unit"] == "m"
    truth = yaml.safe_load(PHANTOM.with_name("phantom_colon.ground_truth.yaml").read_text())
    truth["tracker"]["units"] = "mm"
    (tmp_path / "rig_mm.ground_truth.yaml").write_text(yaml.safe_dump(truth))
    out = tmp_path / "sim.yaml"
    assert main([str(tmp_path / "rig_mm.mcap"), "-o", str(out)]) == 0
    assert load_settings(out).tracker_unit.value == "mm"
    # a truth file from before endo_sim named the unit: metres, as it recorded them
    del truth["tracker"]["units"]
    (tmp_path / "rig_mm.ground_truth.yaml").write_text(yaml.safe_dump(truth))
    assert main([str(tmp_path / "rig_mm.mcap"), "-o", str(out)]) == 0
    assert load_settings(out).tracker_unit.value == "m"


def test_a_recording_without_its_truth_file_is_judged_by_its_pose_error(tmp_path):
    # A re-recording of a simulated bag (endo-replay -> endo-record) carries the
    # ground-truth topics but not the truth file: endo-process scored it in the
    # default world and printed a camera pose error of 1251 mm / 134 deg unexplained.
    rerecorded = tmp_path / "run.mcap"
    message = registration_mismatch(rerecorded, np.eye(4), pose_error_mm=1251.09)
    assert message is not None and "\n" not in message
    assert message.startswith("camera pose error median 1251 mm against the ground truth in "
                              "run.mcap: this run's world")  # fmt: skip
    assert "no run.ground_truth.yaml beside it" in message and "--params sim.yaml" in message
    # the tracker's own error (the phantom's 0.35 mm) or no comparison: nothing to say
    assert registration_mismatch(rerecorded, np.eye(4), pose_error_mm=0.35) is None
    assert registration_mismatch(rerecorded, np.eye(4), pose_error_mm=None) is None
    # with the truth file, the registration itself is compared, as before
    assert "phantom_colon.mcap" in (registration_mismatch(PHANTOM, np.eye(4), 0.35) or "")
