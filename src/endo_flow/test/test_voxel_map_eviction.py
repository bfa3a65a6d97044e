"""Voxel map eviction: a full map holds exactly the voxels a reference LRU model holds."""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import pytest

from endo_flow.voxel_map import VoxelMap


class ReferenceMap:
    """Dictionary model of the map: running means, least recently seen evicted first.

    "Seen" is per insert call: a voxel moves to the newest end on its first
    point of an insert, so the voxels of one frame keep their first-hit order.
    """

    def __init__(self, voxel_size_m: float, capacity: int) -> None:
        self.size = voxel_size_m
        self.capacity = capacity
        self.voxels: OrderedDict[tuple[int, int, int], list[float]] = OrderedDict()
        self.evicted = 0

    def insert(self, points: np.ndarray, grey: np.ndarray) -> None:
        seen: set[tuple[int, int, int]] = set()
        for p, g in zip(points, grey, strict=True):
            key = tuple(int(v) for v in np.floor(p / self.size))
            if key in self.voxels:
                if key not in seen:
                    self.voxels.move_to_end(key)
            else:
                if len(self.voxels) == self.capacity:
                    self.voxels.popitem(last=False)
                    self.evicted += 1
                self.voxels[key] = [0.0, 0.0, 0.0, 0.0, 0]
            seen.add(key)
            v = self.voxels[key]
            v[4] += 1
            for axis in range(3):
                v[axis] += (p[axis] - v[axis]) / v[4]
            v[3] += (g - v[3]) / v[4]


def _compare(m: VoxelMap, ref: ReferenceMap) -> None:
    keys = [tuple(k) for k in m.voxel_keys()[m.recency_order()]]
    assert keys == list(ref.voxels)  # the same voxels, in the same eviction order
    cloud = m.points()
    by_key = {tuple(k): row for row, k in enumerate(m.voxel_keys())}
    rows = np.array([by_key[k] for k in ref.voxels])
    expected = np.array(list(ref.voxels.values()))
    np.testing.assert_allclose(cloud.points[rows], expected[:, :3], rtol=0, atol=1e-7)
    np.testing.assert_allclose(cloud.grey[rows], expected[:, 3], rtol=0, atol=1e-3)
    np.testing.assert_array_equal(cloud.count[rows], expected[:, 4])
    assert m.evicted == ref.evicted


@pytest.mark.parametrize("capacity", [1, 5, 40])
def test_full_map_matches_reference_lru_through_evictions(capacity):
    # small capacities and clustered points: many hash collisions, so the
    # backward-shift deletion moves entries, and many evictions per frame
    rng = np.random.default_rng(7)
    m, ref = VoxelMap(1e-3, capacity), ReferenceMap(1e-3, capacity)
    for frame in range(60):
        centre = rng.uniform(-0.004, 0.004, 3) + np.array([0.001 * frame, 0.0, -0.002])
        points = centre + rng.uniform(-0.003, 0.003, (rng.integers(1, 50), 3))
        grey = rng.uniform(0.0, 255.0, len(points))
        m.insert(points, grey)
        ref.insert(points, grey)
        assert len(m) == len(ref.voxels) <= capacity
        _compare(m, ref)
    assert ref.evicted > 500


def test_every_point_of_a_full_map_is_still_found_after_evictions():
    # fill, evict most of the map, then hit every held voxel again: if a
    # deletion broke a probe chain, a held voxel would be created twice
    rng = np.random.default_rng(3)
    m = VoxelMap(1e-3, 500)
    for _ in range(20):
        m.insert(rng.integers(-30, 30, (300, 3)) * 1e-3 + 5e-4)
    assert m.evicted > 0
    keys = m.voxel_keys()
    assert len(np.unique(keys, axis=0)) == len(m) == 500
    before, evicted = m.points().count.sum(), m.evicted
    m.insert((keys + 0.5) * 1e-3)
    assert len(m) == 500 and m.evicted == evicted  # nothing new, nothing evicted
    assert m.points().count.sum() == before + 500


def test_reset_empties_the_list_too():
    m = VoxelMap(1e-3, 10)
    m.insert(np.arange(30)[:, None] * np.array([[1e-3, 0.0, 0.0]]))
    assert len(m) == 10 and m.evicted == 20
    m.reset()
    assert len(m) == 0 and m.evicted == 0 and len(m.recency_order()) == 0
    m.insert(np.array([[0.0, 0.0, 0.0], [1e-3, 0.0, 0.0]]))
    assert len(m) == 2
    np.testing.assert_array_equal(m.voxel_keys()[m.recency_order()], [[0, 0, 0], [1, 0, 0]])
