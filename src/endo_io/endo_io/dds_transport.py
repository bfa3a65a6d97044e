"""The Fast DDS transport of an endo3d process, chosen before rclpy initialises.

Why: Fast DDS's shared-memory transport has 512 KB segments by default. A
640×480 32FC1 frame (1.2 MB, what ``endo-photometric-correction`` and
``endo-sfs`` publish) does not fit, so it goes over UDP in ~64 KB fragments.
Reliable readers (``endo-record``) get lost fragments resent; best-effort
readers (the SFS node's sensor-data subscription) lose the whole frame with
any one fragment: the SFS node received 13–21 of 90 corrected frames on the
phantom bag that way.

So every node process (:func:`endo_io.process.run_node`) calls
:func:`configure_large_frames` before ``rclpy.init``: unless the user chose a
transport (``FASTRTPS_DEFAULT_PROFILES_FILE``, ``FASTDDS_DEFAULT_PROFILES_FILE``
or ``FASTDDS_BUILTIN_TRANSPORTS`` set) or another RMW than Fast DDS, the
process gets :data:`LARGE_FRAMES_PROFILE`: UDPv4 for discovery and a
shared-memory transport with 64 MB segments, so a frame travels in one piece.
The profile measured better than Fast DDS's own ``LARGE_DATA`` builtin
transports (``bench/bench_dds_transport.py``, ``docs/benchmarks.md``).

Fast DDS reads these variables when the first participant is created, so
setting them in ``os.environ`` (which also calls ``putenv``) before
``rclpy.init`` is enough; child processes inherit them.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass
from pathlib import Path

#: Environment variables through which Fast DDS finds an XML profile file.
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
#: Environment variable naming Fast DDS's builtin transports (DEFAULT, LARGE_DATA, ...).
BUILTIN_TRANSPORTS_VARIABLE = "FASTDDS_BUILTIN_TRANSPORTS"
#: RMW implementations that read Fast DDS profiles.
FASTDDS_RMWS = ("rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp")

#: Shared-memory segment size, bytes: a few full-resolution float frames, and the
#: flow node's map message in one piece for a while (it grows ~0.4 MB per second of
#: a colon sweep: 24 MB after 60 s; 64 MB, too big for it, at the map's 2 M-voxel
#: capacity). With 16 MB the map went as UDP fragments from ~40 s on and the graph
#: skipped more frames (docs/benchmarks.md, session 11); the price is the segments'
#: pages, up to this much per process.
SEGMENT_BYTES = 64 * 1024 * 1024

LARGE_FRAMES_PROFILE = f"""<?xml version="1.0" encoding="UTF-8" ?>
<!-- endo3d: shared memory with {SEGMENT_BYTES // (1024 * 1024)} MB segments (full-size float
     images in one piece), UDPv4 for discovery. Written by endo3d (endo_io.dds_transport). -->
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

#: File name of the profile when endo3d writes it.
PROFILE_FILE_NAME = "fastdds_large_frames.xml"


@dataclass(frozen=True)
class TransportChoice:
    """The transport a process gets, and why.

    Attributes:
        source: ``"endo3d"`` (the large-frame profile set by endo3d),
            ``"user"`` (a variable the user set is kept) or ``"not fastdds"``
            (another RMW: nothing to do).
        description: one line for logs and ``endo-doctor``.
        variables: the transport variables in effect (name -> value).
    """

    source: str
    description: str
    variables: Mapping[str, str]


def user_transport(environ: Mapping[str, str]) -> TransportChoice | None:
    """The transport the user chose in ``environ``, or None when they chose none."""
    rmw = environ.get("RMW_IMPLEMENTATION", "") or FASTDDS_RMWS[0]
    if rmw not in FASTDDS_RMWS:
        return TransportChoice("not fastdds", f"RMW {rmw}: Fast DDS profiles do not apply", {})
    chosen = {
        name: environ[name]
        for name in (*PROFILE_VARIABLES, BUILTIN_TRANSPORTS_VARIABLE)
        if environ.get(name)
    }
    if not chosen:
        return None
    inherited = _endo3d_profile(chosen)
    if inherited is not None:
        return inherited
    text = ", ".join(f"{name}={value}" for name, value in chosen.items())
    return TransportChoice("user", f"Fast DDS transport of the user's choice ({text})", chosen)


def _endo3d_profile(chosen: Mapping[str, str]) -> TransportChoice | None:
    """The choice of a parent endo3d process (its profile file, nothing else), or None."""
    path = chosen.get(PROFILE_VARIABLES[0])
    if path is None or len(chosen) != 1:
        return None
    try:
        if Path(path).read_text() != LARGE_FRAMES_PROFILE:
            return None
    except OSError:
        return None
    return TransportChoice("endo3d", _profile_description(Path(path)), dict(chosen))


def _profile_description(path: Path) -> str:
    return (
        f"Fast DDS large-frame profile {path} (shared memory, "
        f"{SEGMENT_BYTES // (1024 * 1024)} MB segments; UDPv4 for discovery)"
    )


def default_profile_directory() -> Path:
    """Where endo3d writes its profile: a per-user directory under the temp dir."""
    return Path(tempfile.gettempdir()) / f"endo3d-{os.getuid()}"


def write_profile(path: Path) -> Path:
    """Write :data:`LARGE_FRAMES_PROFILE` to ``path`` atomically (concurrent writers are safe)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists() and path.read_text() == LARGE_FRAMES_PROFILE:
        return path
    scratch = path.with_name(f".{path.name}.{os.getpid()}")
    scratch.write_text(LARGE_FRAMES_PROFILE)
    scratch.replace(path)
    return path


def configure_large_frames(
    environ: MutableMapping[str, str] | None = None, *, directory: Path | None = None
) -> TransportChoice:
    """Give this process (and its children) the large-frame transport unless one is chosen.

    Args:
        environ: the environment to read and update; ``os.environ`` by default
            (call this before ``rclpy.init``).
        directory: where the profile file is written;
            :func:`default_profile_directory` by default.

    Returns:
        What the process gets. A transport the user set is kept unchanged.
    """
    env = os.environ if environ is None else environ
    chosen = user_transport(env)
    if chosen is not None:
        return chosen
    path = write_profile((directory or default_profile_directory()) / PROFILE_FILE_NAME)
    env[PROFILE_VARIABLES[0]] = str(path)
    return TransportChoice("endo3d", _profile_description(path), {PROFILE_VARIABLES[0]: str(path)})
