"""The large-frame Fast DDS profile for a group of child processes (``endo-demo``, benches).

The profile and the rule (keep what the user chose, else shared memory with
64 MB segments) live in :mod:`endo_io.dds_transport`, where every node process
applies them to itself before ``rclpy.init``. This module gives a parent the
same environment for its children, with the profile written where the parent
wants it (the demo's output directory), and a line saying what was done.
"""

from __future__ import annotations

from pathlib import Path

from endo_io.dds_transport import (
    LARGE_FRAMES_PROFILE,
    PROFILE_VARIABLES,
    SEGMENT_BYTES,
    configure_large_frames,
)

__all__ = ["LARGE_FRAMES_PROFILE", "PROFILE_VARIABLES", "SEGMENT_BYTES", "with_large_frame_profile"]


def with_large_frame_profile(env: dict[str, str], directory: Path) -> tuple[dict[str, str], str]:
    """``env`` for child processes with the large-frame profile, and what was done.

    A transport the user already configured (a profile file, or
    ``FASTDDS_BUILTIN_TRANSPORTS``) is kept, with a note saying so; otherwise
    the profile is written to ``directory/fastdds_large_frames.xml`` and named
    in ``FASTRTPS_DEFAULT_PROFILES_FILE``.
    """
    child = dict(env)
    choice = configure_large_frames(child, directory=directory)
    if choice.source == "user":
        return env, choice.description + " (kept)"
    return child, choice.description
