"""A Fast DDS profile for moving full-size float images between local processes.

Why: Fast DDS's shared-memory transport has 512 KB segments by default. A
640×480 32FC1 frame (1.2 MB, what ``endo-photometric-correction`` and ``endo-sfs``
publish) does not fit, so it goes over UDP in ~64 KB fragments. Reliable
readers (``endo-record``) get lost fragments resent; best-effort readers
(the SFS node's sensor-data subscription) lose the whole frame with any
fragment. Measured on the phantom bag at 0.25–0.5× (2-core machine): the SFS
node received 13–21 of 90 corrected frames with the defaults, 90 of 90 with
this profile.

The profile keeps UDP for discovery and adds a shared-memory transport with
16 MB segments, so a frame travels in one piece. It is only read by
rmw_fastrtps (the default RMW of Jazzy); other RMWs ignore it.
"""

from __future__ import annotations

from pathlib import Path

#: Environment variables through which Fast DDS finds an XML profile file.
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")

#: Shared-memory segment size, bytes: a few full-resolution float frames.
SEGMENT_BYTES = 16 * 1024 * 1024

LARGE_FRAMES_PROFILE = f"""<?xml version="1.0" encoding="UTF-8" ?>
<!-- endo3d: shared memory with {SEGMENT_BYTES // (1024 * 1024)} MB segments (full-size float
     images in one piece), UDPv4 for discovery. Written by endo-demo. -->
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>endo3d_shm</transport_id>
      <type>SHM</type>
      <segment_size>{SEGMENT_BYTES}</segment_size>
      <port_queue_capacity>1024</port_queue_capacity>
    </transport_descriptor>
    <transport_descriptor>
      <transport_id>endo3d_udp</transport_id>
      <type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="endo3d_large_frames" is_default_profile="true">
    <rtps>
      <userTransports>
        <transport_id>endo3d_shm</transport_id>
        <transport_id>endo3d_udp</transport_id>
      </userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>
</profiles>
"""


def with_large_frame_profile(env: dict[str, str], directory: Path) -> tuple[dict[str, str], str]:
    """``env`` for child processes with the large-frame profile, and what was done.

    A profile the user already configured is kept (returned unchanged, with
    a note saying so); otherwise the profile is written to
    ``directory/fastdds_large_frames.xml`` and named in
    ``FASTRTPS_DEFAULT_PROFILES_FILE``.
    """
    for name in PROFILE_VARIABLES:
        if env.get(name):
            return env, f"Fast DDS profile from {name}={env[name]} (kept)"
    path = directory / "fastdds_large_frames.xml"
    path.write_text(LARGE_FRAMES_PROFILE)
    return dict(env, FASTRTPS_DEFAULT_PROFILES_FILE=str(path)), f"Fast DDS profile {path}"
