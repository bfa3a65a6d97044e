"""Where a calibration file came from: the input it was fitted to and the tool that wrote it.

``photometric.yaml`` (endo-calibrate) and ``handeye.yaml`` (endo-handeye)
both carry a ``provenance`` mapping so that a file found later can be traced
to its recording, and a result that looks wrong can be checked against it::

    provenance:
      input: {file: graycard.mcap, path: /data/graycard.mcap, size_bytes: 2920000, sha256: 9f..}
      tool: {program: endo-calibrate, endo3d_version: 0.1.0, date: 2026-12-01T23:59:00Z,
             command_line: "endo-calibrate --bag graycard.mcap ..."}
      ...                    # what the tool adds: topics, camera_info, card or board

The tools add their own keys beside ``input`` and ``tool``. Loading a file
logs :func:`provenance_summary` at info level; files written before
provenance existed have none and load as before.
"""

from __future__ import annotations

import hashlib
import shlex
import sys
from collections.abc import Sequence
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from endo_io.camera import CameraModel

#: The distribution whose version names the endo3d release (all packages share it).
VERSION_DISTRIBUTION = "endo_io"
#: Bytes read at a time while hashing.
_CHUNK = 1 << 20


def endo3d_version() -> str:
    """The installed endo3d version ("unknown" when the packages are not installed)."""
    try:
        return metadata.version(VERSION_DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return "unknown"


def file_record(path: str | Path) -> dict[str, Any]:
    """Name, absolute path, size and SHA-256 of an input file.

    A directory (a rosbag2 folder) is recorded by its files in name order: the
    size is their sum and the digest covers each file's name and content.

    Args:
        path: the input file or directory.

    Returns:
        ``{file, path, size_bytes, sha256}``.

    Raises:
        OSError: the path cannot be read.
    """
    source = Path(path)
    digest = hashlib.sha256()
    files = sorted(p for p in source.rglob("*") if p.is_file()) if source.is_dir() else [source]
    size = 0
    for item in files:
        if source.is_dir():
            digest.update(str(item.relative_to(source)).encode() + b"\0")
        with item.open("rb") as handle:
            while chunk := handle.read(_CHUNK):
                digest.update(chunk)
                size += len(chunk)
    return {
        "file": source.name,
        "path": str(source.resolve()),
        "size_bytes": size,
        "sha256": digest.hexdigest(),
    }


def tool_record(program: str, argv: Sequence[str] | None = None) -> dict[str, Any]:
    """The program, endo3d version, UTC date and command line of this run.

    Args:
        program: the console script's name (``endo-calibrate``).
        argv: its arguments (default ``sys.argv[1:]``).
    """
    arguments = list(sys.argv[1:] if argv is None else argv)
    return {
        "program": program,
        "endo3d_version": endo3d_version(),
        "date": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "command_line": shlex.join([program, *(str(a) for a in arguments)]),
    }


def camera_record(camera: CameraModel, source: str) -> dict[str, Any]:
    """The camera_info a calibration used, as plain YAML values.

    Args:
        camera: the camera model.
        source: where it came from ("file camera.yaml", "bag topic /endoscope/camera_info").

    Returns:
        ``{source, width, height, distortion_model, K, D}`` (K row-major, 9 numbers).
    """
    return {
        "source": source,
        "width": int(camera.width),
        "height": int(camera.height),
        "distortion_model": camera.distortion_model,
        "K": [float(x) for x in camera.K.ravel()],
        "D": [float(x) for x in camera.D.ravel()],
    }


def provenance_summary(provenance: dict[str, Any] | None) -> str:
    """One line naming a file's input and the run that wrote it (for an info log).

    Returns "no provenance recorded" for files written before provenance existed.
    """
    if not provenance:
        return "no provenance recorded"
    parts = []
    source = provenance.get("input") or {}
    if source:
        digest = str(source.get("sha256", ""))[:12]
        parts.append(f"from {source.get('file', '?')} ({source.get('size_bytes', '?')} bytes, "
                     f"sha256 {digest}…)")
    tool = provenance.get("tool") or {}
    if tool:
        parts.append(f"by {tool.get('program', '?')} {tool.get('endo3d_version', '?')} "
                     f"on {tool.get('date', '?')}")
        if tool.get("command_line"):
            parts.append(f"command: {tool['command_line']}")
    return "; ".join(parts) if parts else "no provenance recorded"
