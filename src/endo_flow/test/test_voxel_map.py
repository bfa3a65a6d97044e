"""Voxel map: running means, bounded memory with eviction, PLY export."""

from __future__ import annotations

import numpy as np
import pytest

from endo_flow.errors import MapExportError
from endo_flow.messages import grey_cloud_cdr
from endo_flow.voxel_map import VoxelMap, write_ply
from endo_io.pointcloud import records_to_pointcloud2_cdr


def test_running_means_per_voxel():
    m = VoxelMap(voxel_size_m=1e-3, max_voxels=100)
    centre = np.array([0.0105, -0.0205, 0.0505])  # voxel centres
    rng = np.random.default_rng(0)
    pts = centre + rng.uniform(-4e-4, 4e-4, (1000, 3))
    grey = rng.uniform(0, 255, 1000)
    m.insert(pts[:500], grey[:500], np.tile([0.0, 0.0, -1.0], (500, 1)))
    m.insert(pts[500:], grey[500:])
    assert len(m) == 1
    cloud = m.points()
    np.testing.assert_allclose(cloud.points[0], pts.mean(axis=0), atol=1e-6)
    assert abs(cloud.grey[0] - grey.mean()) < 1e-3
    assert cloud.count[0] == 1000
    np.testing.assert_allclose(cloud.normals[0], [0.0, 0.0, -1.0], atol=1e-6)
    m.insert(np.array([[np.nan, 0.0, 0.0], [0.1, 0.1, 0.1]]))
    assert len(m) == 2


def test_capacity_is_bounded_and_old_voxels_go_first():
    m = VoxelMap(voxel_size_m=1e-3, max_voxels=1000)
    nbytes = m.nbytes
    for frame in range(10):  # 10 frames of 400 new voxels each
        x = (np.arange(400) + 400 * frame) * 1e-3 + 5e-4
        m.insert(np.stack([x, np.zeros(400), np.zeros(400)], axis=1))
        assert len(m) == min(1000, 400 * (frame + 1))
    assert m.nbytes == nbytes
    assert m.evicted == 3000
    newest = m.points().points[:, 0]
    assert newest.max() > 3.9  # the last frame is there
    assert newest.min() > 3.0  # the first 3000 voxels were evicted, the last 1000 kept
    m.reset()
    assert len(m) == 0


def test_a_frame_inserted_in_bands_gives_the_map_one_insert_gives():
    """insert(continues=True): the same voxels, means, counts and recency, evictions included."""
    rng = np.random.default_rng(5)
    frames = [rng.uniform(0.0, 0.04, (3000, 3)) for _ in range(6)]  # overlapping voxels
    whole, banded = VoxelMap(2e-3, max_voxels=4000), VoxelMap(2e-3, max_voxels=4000)
    for points in frames:
        grey = rng.uniform(0, 255, len(points))
        normals = rng.normal(size=points.shape)
        whole.insert(points, grey, normals)
        for k, band in enumerate(np.array_split(np.arange(len(points)), 7)):
            banded.insert(points[band], grey[band], normals[band], continues=k > 0)
    assert whole.evicted > 0 and whole.evicted == banded.evicted
    np.testing.assert_array_equal(whole.voxel_keys(), banded.voxel_keys())
    np.testing.assert_array_equal(whole.recency_order(), banded.recency_order())
    a, b = whole.points(), banded.points()
    np.testing.assert_array_equal(a.count, b.count)
    for x, y in ((a.points, b.points), (a.grey, b.grey), (a.normals, b.normals)):
        np.testing.assert_array_equal(x, y)
    # without continues each band is a frame of its own: the recency list differs
    separate = VoxelMap(2e-3, max_voxels=4000)
    for points in frames[:2]:
        for band in np.array_split(np.arange(len(points)), 7):
            separate.insert(points[band])
    first_two = VoxelMap(2e-3, max_voxels=4000)
    for points in frames[:2]:
        first_two.insert(points)
    assert not np.array_equal(first_two.recency_order(), separate.recency_order())


@pytest.mark.parametrize("min_count", [1, 3])
def test_published_records_are_the_grey_cloud_of_the_map_bytes_for_bytes(min_count):
    """The map topic's message: grey_cloud_cdr of points()'s positions and grey, byte for byte."""
    rng = np.random.default_rng(8)
    m = VoxelMap(1e-3, max_voxels=50_000)
    for _ in range(4):
        points = rng.uniform(0.0, 0.03, (20_000, 3))
        m.insert(points, rng.uniform(-20.0, 280.0, len(points)))  # clipped at both ends
    m.insert(np.full((1, 3), 0.5), np.array([2.5]))  # a tie rounds half to even: 2
    records, finite = m.published_records(min_count)
    expected = m.points(min_count)
    assert finite and len(records) == len(expected.points) > 1000
    assert (m.points().count < 3).any() and (m.points().count >= 3).any()
    np.testing.assert_array_equal(records["rgb"] >> 16, np.clip(np.rint(expected.grey), 0, 255))
    assert min_count > 1 or records["rgb"][-1] == 0x020202  # the tie, fused from one point
    nan_grey = VoxelMap(1e-3, max_voxels=10)
    nan_grey.insert(np.full((1, 3), 0.7), np.array([np.nan]))  # no grey level: black
    assert nan_grey.published_records()[0]["rgb"].tolist() == [0]
    assert records_to_pointcloud2_cdr(records, 123, "world", is_dense=finite) == (
        grey_cloud_cdr(expected.points, expected.grey, 123, "world"))


def test_a_thinned_map_keeps_an_even_stable_nested_share_of_its_voxels():
    """published_records(fraction=f): ~f of the voxels, spread evenly, the same ones each call."""
    rng = np.random.default_rng(9)
    m = VoxelMap(2.5e-4, max_voxels=200_000)
    # a curved surface of ~70k voxels (a half cylinder of radius 20 mm, 80 mm long)
    angle, z = rng.uniform(0.0, np.pi, 400_000), rng.uniform(0.0, 0.08, 400_000)
    surface = np.stack([0.02 * np.cos(angle), 0.02 * np.sin(angle), z], axis=1)
    m.insert(surface, rng.uniform(0, 255, len(surface)))
    whole, _ = m.published_records()
    n = len(whole)
    assert n == len(m) > 50_000
    xyz = {f: m.published_records(fraction=f)[0][["x", "y", "z"]] for f in (0.5, 0.1, 0.02)}
    for f, kept in xyz.items():
        # binomial: within 5 standard deviations of f * n
        assert abs(len(kept) - f * n) < 5 * np.sqrt(n * f * (1 - f)), (f, len(kept))
        # even: every eighth of the cylinder's length keeps its share
        counts = np.histogram(kept["z"], bins=8, range=(0.0, 0.08))[0]
        whole_counts = np.histogram(whole["z"], bins=8, range=(0.0, 0.08))[0]
        np.testing.assert_allclose(counts / whole_counts, f, rtol=0.25)
    # the same voxels each call, and a smaller share is a subset of a larger one
    again, _ = m.published_records(fraction=0.1)
    assert again.tobytes() == m.published_records(fraction=0.1)[0].tobytes()
    as_set = {f: {tuple(r) for r in kept.tolist()} for f, kept in xyz.items()}
    assert as_set[0.02] <= as_set[0.1] <= as_set[0.5] <= {tuple(r) for r in
                                                         whole[["x", "y", "z"]].tolist()}
    # a voxel's later points change its mean and grey level, not whether it is kept
    m.insert(surface[:1000], np.zeros(1000))
    later = m.published_records(fraction=0.1)[0]

    def voxels(records: np.ndarray) -> set[tuple[int, ...]]:
        xyz = np.stack([records[c] for c in ("x", "y", "z")], axis=1).astype(np.float64)
        return {tuple(v) for v in np.floor(xyz / 2.5e-4).astype(np.int64).tolist()}

    assert (later["rgb"] != again["rgb"]).any() and voxels(later) == voxels(again)
    for bad in (0.0, -0.5, 1.5, float("nan")):
        with pytest.raises(ValueError, match="fraction"):
            m.published_records(fraction=bad)


def test_ply_binary_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.normal(0.0, 0.05, (37, 3)).astype(np.float32)
    normals = rng.normal(0.0, 1.0, (37, 3)).astype(np.float32)
    grey = rng.uniform(0, 255, 37)
    count = np.arange(37, dtype=np.uint32)
    path = tmp_path / "map.ply"
    assert write_ply(path, pts, normals=normals, grey=grey, count=count) == 37
    data = path.read_bytes()
    header, body = data.split(b"end_header\n", 1)
    lines = header.decode().splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "element vertex 37" in lines
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
                      ("nz", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                      ("count", "<u4")])
    vertex = np.frombuffer(body, dtype=dtype)
    np.testing.assert_array_equal(np.stack([vertex["x"], vertex["y"], vertex["z"]], 1), pts)
    np.testing.assert_array_equal(vertex["red"], np.rint(grey).astype(np.uint8))
    np.testing.assert_array_equal(vertex["count"], count)
    with pytest.raises(MapExportError):
        write_ply(path, np.empty((0, 3)))
    with pytest.raises(MapExportError):
        write_ply(tmp_path / "missing" / "x.ply", pts)
