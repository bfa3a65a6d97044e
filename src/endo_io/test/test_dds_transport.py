"""endo_io.dds_transport: the large-frame profile unless the user chose a transport."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest

from endo_io.dds_transport import (
    LARGE_FRAMES_PROFILE,
    SEGMENT_BYTES,
    configure_large_frames,
    write_profile,
)


def test_with_nothing_set_the_profile_is_written_and_named(tmp_path):
    env: dict[str, str] = {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    choice = configure_large_frames(env, directory=tmp_path)
    assert choice.source == "endo3d"
    path = tmp_path / "fastdds_large_frames.xml"
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(path)
    root = ET.fromstring(path.read_text())
    ns = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    shm = [d for d in root.iterfind(".//p:transport_descriptor", ns)
           if d.findtext("p:type", namespaces=ns) == "SHM"]  # fmt: skip
    assert int(shm[0].findtext("p:segment_size", namespaces=ns)) == SEGMENT_BYTES
    participant = root.find(".//p:participant", ns)
    assert participant is not None and participant.get("is_default_profile") == "true"
    # a child of this process inherits the variable and names the same choice
    again = configure_large_frames(dict(env), directory=tmp_path / "elsewhere")
    assert again.source == "endo3d" and again.variables == choice.variables


@pytest.mark.parametrize("name", [
    "FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS",
])  # fmt: skip
def test_a_transport_the_user_set_is_kept(tmp_path, name):
    env = {name: "LARGE_DATA" if name.endswith("TRANSPORTS") else "/etc/mine.xml"}
    before = dict(env)
    choice = configure_large_frames(env, directory=tmp_path)
    assert env == before
    assert choice.source == "user" and name in choice.description
    assert not (tmp_path / "fastdds_large_frames.xml").exists()


def test_another_rmw_is_left_alone(tmp_path):
    env = {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}
    assert configure_large_frames(env, directory=tmp_path).source == "not fastdds"
    assert env == {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}


def test_writing_twice_keeps_one_complete_file(tmp_path):
    path = write_profile(tmp_path / "a" / "p.xml")
    write_profile(path)
    assert path.read_text() == LARGE_FRAMES_PROFILE
    assert [p.name for p in path.parent.iterdir()] == ["p.xml"]
