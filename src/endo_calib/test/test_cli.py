import cv2
import numpy as np
import pytest
import yaml
from std_msgs.msg import Float32

from endo_calib.calibration import PhotometricCalibration
from endo_calib.cli import main


@pytest.fixture(scope="module")
def small_card(synth):
    return synth.make_card(width=96, height=72, peak=1.0)


def _write_manifest(tmp_path, card, frames=4, skip_level=None):
    rng = np.random.default_rng(8)
    levels = []
    for rho in (0.2, 0.35, 0.5, 0.65, 0.8):
        names = []
        if rho != skip_level:
            for i, frame in enumerate(card.frames(rho, frames, rng)):
                name = f"card_{int(rho * 100)}_{i}.png"
                cv2.imwrite(str(tmp_path / name), frame)
                names.append(name)
        levels.append({"reflectance": rho, "images": names})
    card.camera.save_yaml(tmp_path / "camera.yaml")
    manifest = tmp_path / "levels.yaml"
    manifest.write_text(yaml.safe_dump({"camera_info": "camera.yaml", "levels": levels}))
    return manifest


def test_manifest_to_calibration_report_and_dso(tmp_path, small_card, synth, capsys):
    manifest = _write_manifest(tmp_path, small_card)
    out = tmp_path / "out" / "photometric.yaml"
    code = main(
        [
            "--manifest",
            str(manifest),
            "-o",
            str(out),
            "--report",
            str(tmp_path / "calib.png"),
            "--export-dso",
            str(tmp_path / "dso"),
        ]
    )
    assert code == 0, capsys.readouterr().err
    cal = PhotometricCalibration.load(out)
    truth = synth.true_inverse(synth.gamma_response, 8)
    assert np.max(np.abs(cal.inverse_response - truth)[5:251]) < 0.015
    report = cv2.imread(str(tmp_path / "calib.png"))
    assert report is not None and report.shape[0] > 400 and report.std() > 10
    assert (tmp_path / "dso" / "pcalib.txt").is_file()
    # --import-dso converts back into our format
    code = main(["--import-dso", str(tmp_path / "dso"), "-o", str(tmp_path / "from_dso.yaml")])
    assert code == 0
    back = PhotometricCalibration.load(tmp_path / "from_dso.yaml")
    np.testing.assert_allclose(back.inverse_response, cal.inverse_response, atol=1e-5)


def test_an_existing_output_is_refused_without_overwrite(tmp_path, small_card, capsys):
    # -o used to replace the user's calibration (and its light map) silently.
    manifest = _write_manifest(tmp_path, small_card, frames=2)
    out = tmp_path / "photometric.yaml"
    out.write_text("# the user's calibration\n")
    assert main(["--manifest", str(manifest), "-o", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert error == f"endo-calibrate: OutputExistsError: {out} exists; --overwrite replaces it"
    assert out.read_text() == "# the user's calibration\n"
    assert not (tmp_path / "photometric.light_map.png").exists()
    assert main(["--manifest", str(manifest), "-o", str(out), "--overwrite"]) == 0
    assert PhotometricCalibration.load(out).width == 96


def test_manifest_with_a_missing_level_or_image_fails_cleanly(tmp_path, small_card, capsys):
    manifest = _write_manifest(tmp_path, small_card, frames=2, skip_level=0.5)
    assert main(["--manifest", str(manifest), "-o", str(tmp_path / "p.yaml")]) == 2
    assert "InsufficientLevelsError" in capsys.readouterr().err
    manifest = _write_manifest(tmp_path, small_card, frames=2)
    (tmp_path / "card_20_1.png").unlink()
    assert main(["--manifest", str(manifest), "-o", str(tmp_path / "p.yaml")]) == 2
    assert "card_20_1.png not found" in capsys.readouterr().err
    broken = tmp_path / "broken.yaml"
    broken.write_text("levels: [ {reflectance: 0.2, images: [a.png]\n")
    assert main(["--manifest", str(broken)]) == 2
    assert "ManifestError" in capsys.readouterr().err
    assert not (tmp_path / "p.yaml").exists()


def test_bag_input_pairs_images_with_the_gray_level(tmp_path, small_card, synth):
    from endo_io.bag import BagWriter
    from endo_io.image import array_to_image

    rng = np.random.default_rng(9)
    path = tmp_path / "graycard.mcap"
    t = 1_000_000_000
    with BagWriter(path) as bag:
        bag.write_message("/endoscope/camera_info", small_card.camera.to_camera_info(t), t)
        # frames before the first gray level are ignored
        junk = np.full((72, 96), 255, np.uint8)
        bag.write_message(
            "/endoscope/image_raw", array_to_image(junk, "mono8", t - 10**8), t - 10**8
        )
        for rho in (0.2, 0.4, 0.6, 0.8):
            for frame in small_card.frames(rho, 4, rng):
                # as endo_sim records: the level of each frame at the frame's
                # own log time, written just after it
                t += 33_000_000
                bag.write_message("/endoscope/image_raw", array_to_image(frame, "mono8", t), t)
                bag.write_message("/calibration/gray_level", Float32(data=rho), t)
    out = tmp_path / "photometric.yaml"
    assert main(["--bag", str(path), "-o", str(out)]) == 0
    cal = PhotometricCalibration.load(out)
    levels = cal.fit_summary["levels"]
    assert sorted(lv["reflectance"] for lv in levels) == pytest.approx([0.2, 0.4, 0.6, 0.8])
    assert all(lv["frames"] == 4 for lv in levels)
    truth = synth.true_inverse(synth.gamma_response, 8)
    assert np.max(np.abs(cal.inverse_response - truth)[5:251]) < 0.02
