"""A fused point map in ``world``: a bounded hash of voxels with running means, and PLY export.

Every inserted point falls into the voxel floor(p / voxel_size). A voxel
keeps the running mean of the positions and grey levels of its points, the
sum of their normals and their count. Voxels live in dense arrays of at most
``max_voxels`` rows, found through an open-addressing hash table (linear
probing, 2× the capacity) over a packed int64 key (21 bits per axis: ±2²⁰
voxels, ±1 km at 1 mm). Inserting is one numba loop over the points (no
per-point Python).

Memory is fixed at construction. The voxels are also kept in a doubly
linked list in the order they were last seen (a voxel hit by a point moves
to the tail). Once the map is full, each new voxel takes the row of the
voxel at the head, the one seen longest ago, whose table slot is freed by
backward-shift deletion (no tombstones, so the probe lengths stay those of
a table without deletions). Eviction is thus O(1) per new voxel, spread over
the inserts that need room: no insert sorts or rebuilds anything (the
previous batch eviction, an argsort of 2 M stamps and a table rebuild, held
one insert for 0.33 s on a quiet machine and seconds under load).

:func:`write_ply` writes binary little-endian PLY (x, y, z float32 metres,
nx, ny, nz float32, red, green, blue uchar grey, and the count), which 3D
Slicer, MeshLab and CloudCompare read; the map's :meth:`VoxelMap.export_ply`
and the offline processor both call it.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from endo_flow.errors import MapExportError
from endo_io.point_records import XYZRGB_RECORD

_OFFSET = 1 << 20
_MASK = (1 << 21) - 1
_EMPTY = -1
_NONE = np.int32(-1)  # no list neighbour
_HEAD, _TAIL, _EVICTED = 0, 1, 2  # slots of the list state array
_ALL_BITS = np.int64(-1)  # a hash mask keeping all 64 bits


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
def _unlink(index: np.int64, prev: np.ndarray, nxt: np.ndarray, state: np.ndarray) -> None:
    """Take voxel ``index`` out of the recency list."""
    p, n = prev[index], nxt[index]
    if p == -1:
        state[0] = n
    else:
        nxt[p] = n
    if n == -1:
        state[1] = p
    else:
        prev[n] = p


@numba.njit(cache=True, nogil=True)
def _append(index: np.int64, prev: np.ndarray, nxt: np.ndarray, state: np.ndarray) -> None:
    """Put voxel ``index`` at the tail (most recently seen) of the recency list."""
    tail = state[1]
    prev[index] = tail
    nxt[index] = -1
    if tail == -1:
        state[0] = index
    else:
        nxt[tail] = index
    state[1] = index


@numba.njit(cache=True, nogil=True)
def _delete(table: np.ndarray, keys: np.ndarray, index: np.int64) -> None:
    """Free the table slot of voxel ``index`` by backward-shift deletion (linear probing)."""
    mask = np.int64(table.size - 1)
    slot = _hash(keys[index], mask)
    while table[slot] != index:
        slot = (slot + 1) & mask
    hole = slot
    probe = slot
    while True:
        probe = (probe + 1) & mask
        moved = table[probe]
        if moved == _EMPTY:
            break
        home = _hash(keys[moved], mask)
        # the entry at ``probe`` may fill the hole unless its home lies
        # cyclically in (hole, probe]: then the hole is not on its probe path
        stays = hole < home <= probe if hole <= probe else home > hole or home <= probe
        if not stays:
            table[hole] = moved
            hole = probe
    table[hole] = _EMPTY


@numba.njit(cache=True, nogil=True)
def _insert(
    points: np.ndarray, grey: np.ndarray, normals: np.ndarray, has_normals: bool,
    inv_size: float, table: np.ndarray, keys: np.ndarray, mean: np.ndarray,
    mean_grey: np.ndarray, normal_sum: np.ndarray, count: np.ndarray, last: np.ndarray,
    frame: int, prev: np.ndarray, nxt: np.ndarray, state: np.ndarray, n_voxels: int,
) -> tuple[int, int]:
    """Fuse points (N, 3); returns (voxels now held, points skipped as out of range).

    A new voxel in a full map evicts the least recently seen one (the head
    of the recency list) and takes its row.
    """
    mask = np.int64(table.size - 1)
    capacity = keys.size
    skipped = 0
    for i in range(points.shape[0]):
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
            if index == _EMPTY or keys[index] == key:
                break
            slot = (slot + 1) & mask
        if index == _EMPTY:
            if n_voxels < capacity:
                index = n_voxels
                n_voxels += 1
            else:
                index = state[0]  # seen longest ago
                _unlink(index, prev, nxt, state)
                _delete(table, keys, index)
                state[2] += 1
                # the deletion may have shifted entries: find the key's slot anew
                slot = _hash(key, mask)
                while table[slot] != _EMPTY:
                    slot = (slot + 1) & mask
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
            last[index] = frame
            _append(index, prev, nxt, state)
        elif last[index] != frame:  # first hit this frame: now the most recently seen
            last[index] = frame
            _unlink(index, prev, nxt, state)
            _append(index, prev, nxt, state)
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
    return n_voxels, skipped


@numba.njit(cache=True, nogil=True)
def _walk(nxt: np.ndarray, head: int, n: int) -> np.ndarray:
    """The rows of the recency list from ``head`` on: (n,) int64."""
    order = np.empty(n, np.int64)
    index = head
    for k in range(n):
        order[k] = index
        index = nxt[index]
    return order


@numba.njit(cache=True, nogil=True)
def _published(
    keys: np.ndarray, mean: np.ndarray, grey: np.ndarray, count: np.ndarray, n: int,
    min_count: int, below: np.uint64, words: np.ndarray, bits: np.ndarray,
) -> tuple[int, bool]:
    """Write the kept voxels' records; returns (how many, all finite).

    A voxel is kept when fused from at least ``min_count`` points and its
    key's 64-bit hash is below ``below`` (2**64 - 1: every voxel).
    ``words`` (rows, 8) float32 and ``bits`` (rows, 8) uint32 are two views
    of the same zeroed buffer of ``XYZRGB_RECORD``s: x, y, z the voxel's
    mean, rgb its grey level rounded (half to even) and clipped to 0-255 in
    each channel, as ``endo_flow.messages.grey_cloud`` packs a grey level.
    """
    m = 0
    finite = True
    every = below == np.uint64(0xFFFFFFFFFFFFFFFF)
    for i in range(n):
        if count[i] < min_count:
            continue
        if not every and np.uint64(_hash(keys[i], _ALL_BITS)) >= below:
            continue
        for k in range(3):
            words[m, k] = mean[i, k]
            finite = finite and np.isfinite(mean[i, k])
        level = np.rint(np.float64(grey[i]))
        level = min(level, 255.0) if level >= 0.0 else 0.0  # NaN: 0, as astype(uint8) gives
        g = np.uint32(level)
        bits[m, 4] = (g << np.uint32(16)) | (g << np.uint32(8)) | g
        m += 1
    return m, finite


def _hash_bound(fraction: float) -> np.uint64:
    """The 64-bit hash below which a voxel is kept, for a kept share ``fraction`` in (0, 1]."""
    if fraction >= 1.0:
        return np.uint64(0xFFFFFFFFFFFFFFFF)
    return np.uint64(int(fraction * 2.0**64))


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
        max_voxels: capacity; memory is 48 bytes per voxel plus a 16-byte
            table slot per voxel, allocated at construction.
    """

    def __init__(self, voxel_size_m: float = 1e-3, max_voxels: int = 2_000_000) -> None:
        if not voxel_size_m > 0.0:
            raise ValueError(f"voxel_size_m must be > 0, got {voxel_size_m}")
        if not 1 <= max_voxels < 2**31:
            raise ValueError(f"max_voxels must be in [1, 2**31), got {max_voxels}")
        self.voxel_size_m = float(voxel_size_m)
        self.max_voxels = int(max_voxels)
        table_size = 1 << int(np.ceil(np.log2(2 * self.max_voxels)))
        self._table = np.full(table_size, _EMPTY, np.int64)
        self._keys = np.zeros(self.max_voxels, np.int64)
        self._mean = np.zeros((self.max_voxels, 3), np.float32)
        self._grey = np.zeros(self.max_voxels, np.float32)
        self._normal = np.zeros((self.max_voxels, 3), np.float32)
        self._count = np.zeros(self.max_voxels, np.uint32)
        self._last = np.zeros(self.max_voxels, np.int32)  # insert call that last hit the voxel
        self._frame = 0
        # the recency list: previous and next voxel rows, -1 at the ends
        self._prev = np.full(self.max_voxels, _NONE, np.int32)
        self._next = np.full(self.max_voxels, _NONE, np.int32)
        self._state = np.array([_NONE, _NONE, 0], np.int64)  # head, tail, evicted
        self._n = 0
        self.skipped = 0
        #: changes with every reset and every insert that took points in (a publisher
        #: compares it with the revision it last sent); only equality matters
        self.revision = 0

    def __len__(self) -> int:
        return self._n

    @property
    def evicted(self) -> int:
        """Voxels evicted to make room since construction (or the last reset)."""
        return int(self._state[_EVICTED])

    @property
    def nbytes(self) -> int:
        """Memory held by the map's arrays, bytes (fixed at construction)."""
        arrays = (self._table, self._keys, self._mean, self._grey, self._normal, self._count,
                  self._last, self._prev, self._next)
        return int(sum(a.nbytes for a in arrays))

    def reset(self) -> None:
        """Empty the map (memory stays allocated)."""
        self._table[:] = _EMPTY
        self._state[:] = (_NONE, _NONE, 0)
        if self._n:  # emptying an empty map changes nothing a subscriber sees
            self.revision += 1
        self._n = 0

    def insert(
        self,
        points: np.ndarray,
        grey: np.ndarray | None = None,
        normals: np.ndarray | None = None,
        *,
        continues: bool = False,
    ) -> None:
        """Fuse one frame's points.

        Args:
            points: (N, 3) float world points, metres; non-finite ones are
                ignored.
            grey: (N,) grey levels 0–255, or None (0).
            normals: (N, 3) unit normals in world, or None.
            continues: the points are more of the previous insert's frame (a
                frame fused in bands): a voxel that insert moved to the
                recency list's tail is not moved again, so the bands give
                the map one insert of all their points gives.
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
        # a voxel hit several times in one insert moves to the list's tail once;
        # the stamp wraps after 2**31 inserts (2 years at 30 Hz), only equality matters
        if not continues:
            self._frame = (self._frame + 1) & 0x7FFFFFFF
        self._n, skipped = _insert(
            xyz, level, nrm, has_normals, 1.0 / self.voxel_size_m, self._table, self._keys,
            self._mean, self._grey, self._normal, self._count, self._last, self._frame,
            self._prev, self._next, self._state, self._n,
        )
        self.skipped += skipped
        if n > skipped:
            self.revision += 1

    def recency_order(self) -> np.ndarray:
        """Row indices of the held voxels, from the one seen longest ago to the newest: (n,) int64.

        The order in which a full map evicts them.
        """
        return _walk(self._next, int(self._state[_HEAD]), self._n)

    def voxel_keys(self) -> np.ndarray:
        """(n, 3) int64 voxel coordinates floor(p / voxel_size) of the held voxels, by row."""
        keys = self._keys[: self._n]
        return np.stack([((keys >> shift) & _MASK) - _OFFSET for shift in (42, 21, 0)], axis=1)

    def points(self, min_count: int = 1) -> MapPoints:
        """The voxels fused from at least ``min_count`` points, in row order."""
        n = self._n
        keep = self._count[:n] >= min_count
        normal = self._normal[:n][keep]  # boolean indexing copies: normalised in place
        length = np.sqrt((normal * normal).sum(axis=1))
        with np.errstate(invalid="ignore", divide="ignore"):
            normal /= length[:, None]
        normal[~(length > 0.0)] = 0.0
        return MapPoints(self._mean[:n][keep], normal, self._grey[:n][keep],
                         self._count[:n][keep])

    def published_records(self, min_count: int = 1, *, fraction: float = 1.0
                          ) -> tuple[np.ndarray, bool]:
        """The voxels fused from at least ``min_count`` points as point records, in row order.

        What the map topic carries: ((M,) ``endo_io.point_records.XYZRGB_RECORD``
        records, the mean position and the grey level packed as rgb; whether
        every position is finite), written by one pass over the map, for
        :func:`endo_io.pointcloud.records_to_pointcloud2_cdr`. The same
        bytes as ``grey_cloud_cdr`` of :meth:`points`' positions and grey
        levels (tested), without its normals and copies: 24 MB of map took
        ~50 ms of the flow node's thread that way, every map period.

        Args:
            min_count: voxels fused from fewer points are left out.
            fraction: in (0, 1], the share of the voxels kept (1: all). A
                voxel is kept when the hash of its coordinates, as a number
                in [0, 1), is below ``fraction``: a spatially even thinning
                that keeps the same voxels from one call to the next, and
                whose kept set only shrinks as ``fraction`` does (a live
                view thinned as the map grows does not flicker).
        """
        if not 0.0 < fraction <= 1.0:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}")
        n = self._n
        words = np.zeros((n, XYZRGB_RECORD.itemsize // 4), np.float32)
        m, finite = _published(self._keys, self._mean, self._grey, self._count, n,
                               int(min_count), _hash_bound(fraction), words,
                               words.view(np.uint32))
        return words[:m].view(XYZRGB_RECORD).reshape(-1), bool(finite)

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
        # a PLY cut short (a full disk) claims vertices it does not hold: leave none
        with contextlib.suppress(OSError):
            Path(path).unlink()
        raise MapExportError(f"cannot write {path}: {error.strerror or error}") from error
    return m
