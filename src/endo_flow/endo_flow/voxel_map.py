"""A fused point map in ``world``: a bounded hash of voxels with running means, and PLY export.

Every inserted point falls into the voxel floor(p / voxel_size). A voxel
keeps the running mean of the positions and grey levels of its points, the
sum of their normals, their count and the frame it was last seen in. Voxels
live in dense arrays of at most ``max_voxels`` rows, found through an
open-addressing hash table (linear probing, 2× the capacity) over a packed
int64 key (21 bits per axis: ±2²⁰ voxels, ±1 km at 1 mm). Inserting is one
numba loop over the points (no per-point Python); when an insert would
overflow the capacity, the voxels seen longest ago are evicted first (down
to ``evict_to`` of the capacity) and the table is rebuilt, so memory is
fixed at construction.

:func:`write_ply` writes binary little-endian PLY (x, y, z float32 metres,
nx, ny, nz float32, red, green, blue uchar grey, and the count), which 3D
Slicer, MeshLab and CloudCompare read; the map's :meth:`VoxelMap.export_ply`
and the offline processor both call it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from endo_flow.errors import MapExportError

_OFFSET = 1 << 20
_MASK = (1 << 21) - 1
_EMPTY = -1


@numba.njit(cache=True, nogil=True)
def _hash(key: np.int64, mask: np.int64) -> np.int64:
    # SplitMix64 finaliser: spreads neighbouring voxel keys over the table
    x = np.uint64(key)
    x ^= x >> np.uint64(30)
    x *= np.uint64(0xBF58476D1CE4E5B9)
    x ^= x >> np.uint64(27)
    x *= np.uint64(0x94D049BB133111EB)
    x ^= x >> np.uint64(31)
    return np.int64(x & np.uint64(mask))


@numba.njit(cache=True, nogil=True)
def _insert(
    points: np.ndarray, grey: np.ndarray, normals: np.ndarray, has_normals: bool,
    inv_size: float, frame: int, table: np.ndarray, keys: np.ndarray, mean: np.ndarray,
    mean_grey: np.ndarray, normal_sum: np.ndarray, count: np.ndarray, last: np.ndarray,
    n_voxels: int, start: int,
) -> tuple[int, int, int]:
    """Insert points[start:] (N, 3) until one needs a new voxel and the arrays are full.

    Returns (voxels now held, index of the point that found no room or N,
    points skipped as out of range).
    """
    mask = np.int64(table.size - 1)
    capacity = keys.size
    skipped = 0
    for i in range(start, points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        ix = np.int64(np.floor(x * inv_size)) + _OFFSET
        iy = np.int64(np.floor(y * inv_size)) + _OFFSET
        iz = np.int64(np.floor(z * inv_size)) + _OFFSET
        if ix < 0 or iy < 0 or iz < 0 or ix > _MASK or iy > _MASK or iz > _MASK:
            skipped += 1
            continue
        key = (ix << 42) | (iy << 21) | iz
        slot = _hash(key, mask)
        while True:
            index = table[slot]
            if index == _EMPTY:
                if n_voxels >= capacity:
                    return n_voxels, i, skipped
                index = n_voxels
                n_voxels += 1
                table[slot] = index
                keys[index] = key
                mean[index, 0] = 0.0
                mean[index, 1] = 0.0
                mean[index, 2] = 0.0
                mean_grey[index] = 0.0
                normal_sum[index, 0] = 0.0
                normal_sum[index, 1] = 0.0
                normal_sum[index, 2] = 0.0
                count[index] = 0
                break
            if keys[index] == key:
                break
            slot = (slot + 1) & mask
        c = count[index] + 1
        count[index] = c
        f = 1.0 / c
        mean[index, 0] += (x - mean[index, 0]) * f
        mean[index, 1] += (y - mean[index, 1]) * f
        mean[index, 2] += (z - mean[index, 2]) * f
        mean_grey[index] += (grey[i] - mean_grey[index]) * f
        if has_normals and np.isfinite(normals[i, 0]):
            normal_sum[index, 0] += normals[i, 0]
            normal_sum[index, 1] += normals[i, 1]
            normal_sum[index, 2] += normals[i, 2]
        last[index] = frame
    return n_voxels, points.shape[0], skipped


@numba.njit(cache=True, nogil=True)
def _rebuild(table: np.ndarray, keys: np.ndarray, n_voxels: int) -> None:
    """Refill the hash table from the first ``n_voxels`` keys."""
    table[:] = _EMPTY
    mask = np.int64(table.size - 1)
    for index in range(n_voxels):
        slot = _hash(keys[index], mask)
        while table[slot] != _EMPTY:
            slot = (slot + 1) & mask
        table[slot] = index


@dataclass(frozen=True)
class MapPoints:
    """The map's voxels as arrays.

    Attributes:
        points: (M, 3) float32 mean positions, metres, world.
        normals: (M, 3) float32 unit normals (zeros where none were given).
        grey: (M,) float32 mean grey level, 0–255.
        count: (M,) uint32 points fused per voxel.
    """

    points: np.ndarray
    normals: np.ndarray
    grey: np.ndarray
    count: np.ndarray


class VoxelMap:
    """Fused voxel map (see the module docstring).

    Args:
        voxel_size_m: voxel edge, metres.
        max_voxels: capacity; memory is about 44 bytes per voxel plus a
            16-byte table slot per voxel.
        evict_to: after an eviction at most this fraction of the capacity
            is held, (0, 1).
    """

    def __init__(
        self, voxel_size_m: float = 1e-3, max_voxels: int = 2_000_000, evict_to: float = 0.8
    ) -> None:
        if not voxel_size_m > 0.0:
            raise ValueError(f"voxel_size_m must be > 0, got {voxel_size_m}")
        if max_voxels < 1:
            raise ValueError(f"max_voxels must be >= 1, got {max_voxels}")
        if not 0.0 < evict_to < 1.0:
            raise ValueError(f"evict_to must be in (0, 1), got {evict_to}")
        self.voxel_size_m = float(voxel_size_m)
        self.max_voxels = int(max_voxels)
        self.evict_to = float(evict_to)
        table_size = 1 << int(np.ceil(np.log2(2 * self.max_voxels)))
        self._table = np.full(table_size, _EMPTY, np.int64)
        self._keys = np.zeros(self.max_voxels, np.int64)
        self._mean = np.zeros((self.max_voxels, 3), np.float32)
        self._grey = np.zeros(self.max_voxels, np.float32)
        self._normal = np.zeros((self.max_voxels, 3), np.float32)
        self._count = np.zeros(self.max_voxels, np.uint32)
        self._last = np.zeros(self.max_voxels, np.int64)
        self._n = 0
        self._frame = 0
        self.evicted = 0
        self.skipped = 0

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Memory held by the map's arrays, bytes (fixed at construction)."""
        arrays = (self._table, self._keys, self._mean, self._grey, self._normal, self._count,
                  self._last)
        return int(sum(a.nbytes for a in arrays))

    def reset(self) -> None:
        """Empty the map (memory stays allocated)."""
        self._table[:] = _EMPTY
        self._n = 0
        self._frame = 0

    def insert(
        self,
        points: np.ndarray,
        grey: np.ndarray | None = None,
        normals: np.ndarray | None = None,
    ) -> None:
        """Fuse one frame's points.

        Args:
            points: (N, 3) float world points, metres; non-finite ones are
                ignored.
            grey: (N,) grey levels 0–255, or None (0).
            normals: (N, 3) unit normals in world, or None.
        """
        xyz = np.ascontiguousarray(points, np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"points must be (N, 3), got {xyz.shape}")
        n = len(xyz)
        level = np.zeros(n) if grey is None else np.ascontiguousarray(grey, np.float64)
        has_normals = normals is not None
        nrm = np.ascontiguousarray(normals, np.float64) if has_normals else np.zeros((1, 3))
        if len(level) != n or (has_normals and nrm.shape != (n, 3)):
            raise ValueError("grey and normals must have one row per point")
        self._frame += 1
        start = 0
        while start < n:
            self._n, start, skipped = _insert(
                xyz, level, nrm, has_normals, 1.0 / self.voxel_size_m, self._frame, self._table,
                self._keys, self._mean, self._grey, self._normal, self._count, self._last,
                self._n, start,
            )
            self.skipped += skipped
            if start < n:  # full: make room, keeping the voxels seen last
                self._evict(int(self.evict_to * self.max_voxels))

    def _evict(self, keep: int) -> None:
        """Keep the ``keep`` voxels seen most recently; rebuild the table."""
        if self._n <= keep:
            return
        order = np.argsort(-self._last[: self._n], kind="stable")[:keep]
        order.sort()
        for array in (self._keys, self._mean, self._grey, self._normal, self._count, self._last):
            array[:keep] = array[order]
        self.evicted += self._n - keep
        self._n = keep
        _rebuild(self._table, self._keys, self._n)

    def points(self, min_count: int = 1) -> MapPoints:
        """The voxels fused from at least ``min_count`` points."""
        n = self._n
        keep = self._count[:n] >= min_count
        normal = self._normal[:n][keep]
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            unit = np.where(length > 0.0, normal / length, 0.0).astype(np.float32)
        return MapPoints(self._mean[:n][keep].copy(), unit, self._grey[:n][keep].copy(),
                         self._count[:n][keep].copy())

    def export_ply(self, path: str | Path, min_count: int = 1) -> int:
        """Write the map to binary PLY (see :func:`write_ply`); returns the vertex count."""
        cloud = self.points(min_count)
        return write_ply(path, cloud.points, normals=cloud.normals, grey=cloud.grey,
                         count=cloud.count)


def write_ply(
    path: str | Path,
    points: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    grey: np.ndarray | None = None,
    count: np.ndarray | None = None,
    comment: str = "endo3d map, metres, frame world",
) -> int:
    """Write a point set as binary little-endian PLY.

    Args:
        path: output file (parent must exist).
        points: (M, 3) float positions, metres.
        normals: (M, 3) float unit normals, or None.
        grey: (M,) grey levels 0–255 written as red = green = blue, or None.
        count: (M,) points fused per vertex, written as ``uint count``, or
            None.
        comment: a header comment line.

    Returns:
        The number of vertices written.

    Raises:
        MapExportError: nothing to write, mismatched rows, or the file cannot
            be written.
    """
    xyz = np.asarray(points, np.float32)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise MapExportError(f"points must be (M, 3), got {xyz.shape}")
    m = len(xyz)
    if m == 0:
        raise MapExportError("the map is empty: nothing to export")
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if grey is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if count is not None:
        fields += [("count", "<u4")]
    vertex = np.zeros(m, dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for name, column, values in (("normals", ("nx", "ny", "nz"), normals),):
        if values is not None:
            array = np.asarray(values, np.float32)
            if array.shape != (m, 3):
                raise MapExportError(f"{name} must be ({m}, 3), got {array.shape}")
            for axis, key in enumerate(column):
                vertex[key] = array[:, axis]
    if grey is not None:
        level = np.asarray(grey, np.float64)
        if level.shape != (m,):
            raise MapExportError(f"grey must be ({m},), got {level.shape}")
        byte = np.clip(np.rint(level), 0, 255).astype(np.uint8)
        vertex["red"] = vertex["green"] = vertex["blue"] = byte
    if count is not None:
        counts = np.asarray(count)
        if counts.shape != (m,):
            raise MapExportError(f"count must be ({m},), got {counts.shape}")
        vertex["count"] = counts
    types = {"<f4": "float", "u1": "uchar", "<u4": "uint"}
    header = ["ply", "format binary_little_endian 1.0", f"comment {comment}",
              f"element vertex {m}"]
    header += [f"property {types[t]} {name}" for name, t in fields]
    header.append("end_header")
    try:
        with Path(path).open("wb") as stream:
            stream.write(("\n".join(header) + "\n").encode("ascii"))
            stream.write(vertex.tobytes())
    except OSError as error:
        raise MapExportError(f"cannot write {path}: {error.strerror or error}") from error
    return m
