"""endo-calibrate's report figure and the provenance of photometric.yaml.

A small gray-card bag whose brightest card (ρ = 0.8) saturates at the centre
of the view, with a simulator-style truth file beside it.
"""

import hashlib
import logging

import numpy as np
import pytest
import yaml
from std_msgs.msg import Float32

from endo_calib import fit_gray_card
from endo_calib.calibration import PhotometricCalibration
from endo_calib.cli import main
from endo_calib.gray_levels import GrayLevel
from endo_calib.report import SATURATED_NOTE, report_figure

LEVELS = (0.2, 0.35, 0.5, 0.65, 0.8)


@pytest.fixture(scope="module")
def bright_card(synth):
    """The 0.8 card 8 % over full scale at its brightest: its centre saturates."""
    return synth.make_card(width=96, height=72, peak=1.08)


@pytest.fixture(scope="module")
def bag(tmp_path_factory, bright_card, synth):
    from endo_io.bag import BagWriter
    from endo_io.image import array_to_image

    folder = tmp_path_factory.mktemp("bag")
    path = folder / "cards.mcap"
    rng = np.random.default_rng(21)
    t = 1_000_000_000
    with BagWriter(path) as writer:
        writer.write_message("/endoscope/camera_info", bright_card.camera.to_camera_info(t), t)
        for rho in LEVELS:
            for frame in bright_card.frames(rho, 4, rng):
                t += 33_000_000
                writer.write_message("/endoscope/image_raw", array_to_image(frame, "mono8", t), t)
                writer.write_message("/calibration/gray_level", Float32(data=rho), t)
    np.save(folder / "cards.inverse_response.npy", synth.true_inverse(synth.gamma_response, 8))
    return path


@pytest.fixture(scope="module")
def calibrated(bag, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    yaml_path, png = out / "photometric.yaml", out / "calib.png"
    argv = ["--bag", str(bag), "--card-distance", "0.05", "-o", str(yaml_path)]
    argv += ["--report", str(png)]
    assert main(argv) == 0
    return yaml_path, png


def test_provenance_is_written_and_round_trips(bag, calibrated, caplog):
    yaml_path, _ = calibrated
    document = yaml.safe_load(yaml_path.read_text())
    provenance = document["provenance"]
    data = bag.read_bytes()
    assert provenance["input"]["file"] == "cards.mcap"
    assert provenance["input"]["size_bytes"] == len(data)
    assert provenance["input"]["sha256"] == hashlib.sha256(data).hexdigest()
    assert provenance["topics"] == {
        "image": "/endoscope/image_raw",
        "gray_level": "/calibration/gray_level",
        "camera_info": "/endoscope/camera_info",
    }
    assert provenance["camera_info"]["source"] == "bag topic /endoscope/camera_info"
    assert (provenance["camera_info"]["width"], provenance["camera_info"]["height"]) == (96, 72)
    assert provenance["card"]["distance_m"] == 0.05
    tool = provenance["tool"]
    assert tool["program"] == "endo-calibrate" and tool["endo3d_version"]
    assert tool["command_line"].startswith("endo-calibrate --bag ")
    assert tool["date"].endswith("Z")
    assert document["response_range"]["mono"]["saturation_observed"] is True
    with caplog.at_level(logging.INFO, logger="endo_calib.calibration"):
        loaded = PhotometricCalibration.load(yaml_path)
    assert loaded.provenance == provenance
    assert loaded.response_ranges == document["response_range"]
    assert "from cards.mcap" in caplog.text and provenance["input"]["sha256"][:12] in caplog.text
    # saved again, it is the same
    again = loaded.save(yaml_path.with_name("again.yaml"))
    assert yaml.safe_load(again.read_text())["provenance"] == provenance


def test_a_file_without_provenance_still_loads(calibrated, tmp_path, caplog):
    yaml_path, _ = calibrated
    document = yaml.safe_load(yaml_path.read_text())
    for key in ("provenance", "response_range"):
        del document[key]
    old = tmp_path / "old.yaml"
    old.write_text(yaml.safe_dump(document, sort_keys=False))
    (tmp_path / document["light_map"]["file"]).write_bytes(
        yaml_path.with_name(document["light_map"]["file"]).read_bytes()
    )
    with caplog.at_level(logging.INFO, logger="endo_calib.calibration"):
        loaded = PhotometricCalibration.load(old)
    assert loaded.provenance == {} and loaded.response_ranges == {}
    assert loaded.observed_top("mono") is None
    assert "no provenance recorded" in caplog.text
    frame = np.full((72, 96), 120, np.uint8)
    np.testing.assert_array_equal(
        np.isnan(loaded.correct(frame)), np.isnan(loaded.correct(frame, mask_extrapolated=True))
    )


def test_the_report_png_is_written(calibrated):
    import cv2

    _, png = calibrated
    image = cv2.imread(str(png))
    assert image is not None and image.shape[0] >= 600 and image.shape[1] >= 1400
    assert image.std() > 10


def test_report_content(bright_card, synth, bag, calibrated):
    rng = np.random.default_rng(22)
    levels = [GrayLevel(rho, bright_card.frames(rho, 4, rng)) for rho in LEVELS]
    report = fit_gray_card(levels, bright_card.camera)
    truth = synth.true_inverse(synth.gamma_response, 8)
    provenance = PhotometricCalibration.load(calibrated[0]).provenance
    figure = report_figure(report, truth_inverse_response=truth, inputs=provenance)
    axes = {ax.get_label(): ax for ax in figure.axes}
    # value axes stay within the data's range: 0..255 DN, g in 0..1
    assert axes["response"].get_ylim() == (0.0, 255.0)
    assert axes["inverse"].get_xlim() == (0.0, 255.0)
    assert axes["inverse"].get_ylim() == (0.0, 1.0)
    # every card is plotted or annotated: the saturated 0.8 card is annotated
    notes = [t.get_text() for t in axes["response"].texts]
    assert any(SATURATED_NOTE in n and "0.8" in n for n in notes), notes
    points = [line for line in axes["response"].lines if line.get_marker() == "o"]
    plotted = sum(len(line.get_xdata()) for line in points)
    assert plotted + len(notes) == len(LEVELS)
    # legends, truth overlay, perceptual colour maps with colour bars
    for name in ("response", "inverse"):
        assert axes[name].get_legend() is not None
    labels = [line.get_label() for line in axes["inverse"].lines]
    assert "truth (simulator)" in labels
    for name in ("light", "before", "after", "residual"):
        assert axes[name].images[0].get_cmap().name in ("viridis", "cividis")
    colour_bars = [ax for ax in figure.axes if ax.get_label() == "<colorbar>"]
    assert len(colour_bars) == 5  # reflectance of the samples + four images
    # inputs and fit statistics as text
    text = "\n".join(t.get_text() for t in axes["text"].texts)
    for field in ("cards.mcap", "sha256", "topic image: /endoscope/image_raw", "camera_info:",
                  "card distance: 50.0 mm", "residual RMS", "observed raw values",
                  "ρ=0.8", SATURATED_NOTE):
        assert field in text, field
    import matplotlib.pyplot as plt

    plt.close(figure)
