"""The shipped Foxglove layout and RViz2 config name only topics and frames the graph has.

Every topic a panel or display subscribes to must be one of endo_io.topics'
names (what the graph publishes), and every frame one of its REP 103
frames; the layout's topics must also be channels endo-foxglove serves, so
the layout works live as well as on a recording. A renamed topic in
endo_io.topics fails here instead of leaving an empty panel.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from endo_foxglove.node import STREAMS, TF_CHANNEL, TF_STATIC_CHANNEL
from endo_io import topics

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / "config" / "foxglove" / "endo3d.json"
RVIZ = ROOT / "config" / "rviz" / "endo3d.rviz"

GRAPH_TOPICS = {v for k, v in vars(topics).items() if k.isupper() and v.startswith("/")}
GRAPH_FRAMES = {v for k, v in vars(topics).items() if k.endswith("_FRAME")}
BRIDGE_CHANNELS = {s.topic for s in STREAMS} | {TF_CHANNEL, TF_STATIC_CHANNEL}

# Layout keys whose string value names a topic, a message path or a frame.
_TOPIC_KEYS = {"imageTopic", "calibrationTopic", "topicToRender"}
_PATH_KEYS = {"value"}  # plot series: "/topic.field"
_FRAME_KEYS = {"followTf", "frameId", "Fixed Frame", "Target Frame", "Reference Frame"}


def _walk(node: Any, key: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(node, dict):
        for k, v in node.items():
            yield k, v
            yield from _walk(v, k)
    elif isinstance(node, list):
        for item in node:
            yield from _walk(item, key)


def layout_references() -> tuple[set[str], set[str]]:
    layout = json.loads(LAYOUT.read_text())
    found_topics: set[str] = set()
    frames: set[str] = set()
    for key, value in _walk(layout["configById"]):
        if key in _TOPIC_KEYS and isinstance(value, str):
            found_topics.add(value)
        elif key in _PATH_KEYS and isinstance(value, str) and value.startswith("/"):
            found_topics.add(value.split(".", 1)[0])
        elif key == "topics" and isinstance(value, dict):
            found_topics.update(value)
        elif key == "transforms" and isinstance(value, dict):
            frames.update(k.removeprefix("frame:") for k in value if k.startswith("frame:"))
        elif key in _FRAME_KEYS and isinstance(value, str):
            frames.add(value)
    return found_topics, frames


def rviz_references() -> tuple[set[str], set[str]]:
    config = yaml.safe_load(RVIZ.read_text())
    found_topics: set[str] = set()
    frames: set[str] = set()
    for key, value in _walk(config):
        if key == "Topic" and isinstance(value, dict):
            found_topics.add(value["Value"])
        elif key in _FRAME_KEYS and isinstance(value, str) and value != "<Fixed Frame>":
            frames.add(value)
    return found_topics, frames


def test_layout_is_a_foxglove_layout_whose_panels_all_appear():
    layout = json.loads(LAYOUT.read_text())
    panels = set(layout["configById"])

    def leaves(node: Any) -> Iterator[str]:
        if isinstance(node, str):
            yield node
        else:
            yield from leaves(node["first"])
            yield from leaves(node["second"])

    assert set(leaves(layout["layout"])) == panels
    kinds = {panel.split("!")[0] for panel in panels}
    assert {"Image", "3D", "Plot", "DiagnosticSummary"} <= kinds


def test_layout_references_only_graph_topics_and_frames_the_bridge_serves():
    found_topics, frames = layout_references()
    assert found_topics, "no topic found: the walker no longer reads the layout"
    assert found_topics <= GRAPH_TOPICS, found_topics - GRAPH_TOPICS
    assert found_topics <= BRIDGE_CHANNELS, found_topics - BRIDGE_CHANNELS
    assert frames <= GRAPH_FRAMES, frames - GRAPH_FRAMES
    assert topics.WORLD_FRAME in frames


def test_layout_shows_what_the_issue_asks_for():
    layout = json.loads(LAYOUT.read_text())["configById"]
    images = {v["imageMode"]["imageTopic"]: v["imageMode"] for k, v in layout.items()
              if k.startswith("Image!")}
    assert images[topics.DEPTH]["colorMode"] == "colormap"
    scene = next(v for k, v in layout.items() if k.startswith("3D!"))
    assert {topics.POINTS, topics.MAP, topics.CAMERA_INFO} <= set(scene["topics"])
    assert scene["followTf"] == topics.WORLD_FRAME
    plot = next(v for k, v in layout.items() if k.startswith("Plot!"))
    assert any(p["value"].startswith(topics.SCALE + ".") for p in plot["paths"])


def test_rviz_config_fixed_frame_world_best_effort_clouds_pose_and_images():
    config = yaml.safe_load(RVIZ.read_text())["Visualization Manager"]
    assert config["Global Options"]["Fixed Frame"] == topics.WORLD_FRAME
    displays = {d["Topic"]["Value"]: d for d in config["Displays"] if "Topic" in d}
    points = displays[topics.POINTS]
    assert points["Class"] == "rviz_default_plugins/PointCloud2"
    assert points["Topic"]["Reliability Policy"] == "Best Effort"
    assert displays[topics.MAP]["Topic"]["Durability Policy"] == "Transient Local"
    assert displays[topics.CAMERA_POSE]["Class"] == "rviz_default_plugins/Pose"
    assert any(d["Class"] == "rviz_default_plugins/Image" for d in displays.values())


@pytest.mark.parametrize("references", [layout_references, rviz_references])
def test_configs_reference_only_graph_names(references):
    found_topics, frames = references()
    assert found_topics and found_topics <= GRAPH_TOPICS, found_topics - GRAPH_TOPICS
    assert frames <= GRAPH_FRAMES, frames - GRAPH_FRAMES
