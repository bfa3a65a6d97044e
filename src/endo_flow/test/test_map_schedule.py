"""The map's publishing budget: the interval grows with the last message's bytes."""

from __future__ import annotations

import itertools

import pytest

from endo_flow.map_schedule import MapPublishSchedule


def sends(schedule: MapPublishSchedule, sizes: list[int], seconds: float,
          frame_s: float = 1 / 30) -> list[float]:
    """Times the map goes when asked after every frame, each message the next size."""
    sent: list[float] = []
    for k in range(int(seconds / frame_s) + 1):
        now = k * frame_s
        if schedule.due(now):
            schedule.published(now, sizes[min(len(sent), len(sizes) - 1)])
            sent.append(now)
    return sent


def test_small_maps_go_every_period() -> None:
    sent = sends(MapPublishSchedule(2.0, 4.0), [1_000_000], 10.0)
    assert sent == pytest.approx([0.0, 2.0, 4.0, 6.0, 8.0, 10.0], abs=1 / 30)
    assert all(b - a >= 2.0 for a, b in itertools.pairwise(sent))


def test_a_large_map_waits_its_bytes_over_the_bandwidth() -> None:
    # 24 MB at 4 MB/s: 6 s between messages
    schedule = MapPublishSchedule(2.0, 4.0)
    assert schedule.interval_s(24_000_000) == pytest.approx(6.0)
    sent = sends(schedule, [24_000_000], 600.0)
    assert sent[:4] == pytest.approx([0.0, 6.0, 12.0, 18.0], abs=1 / 30)
    # the average rate stays within the budget
    rate = 24.0 * (len(sent) - 1) / (sent[-1] - sent[0])
    assert 3.97 < rate <= 4.0


def test_growing_map_interval_follows_the_last_message() -> None:
    sent = sends(MapPublishSchedule(1.0, 2.0), [1_000_000, 4_000_000, 10_000_000], 30.0,
                 frame_s=0.25)
    # 1 MB -> 1 s (the period), 4 MB -> 2 s, 10 MB -> 5 s
    assert sent[:5] == [0.0, 1.0, 3.0, 8.0, 13.0]


def test_zero_bandwidth_falls_back_to_the_period() -> None:
    assert sends(MapPublishSchedule(2.0, 0.0), [64_000_000], 6.0, frame_s=0.5) == [
        0.0, 2.0, 4.0, 6.0]


@pytest.mark.parametrize(("period", "bandwidth"), [(0.0, 1.0), (-1.0, 1.0), (1.0, -0.5),
                                                   (1.0, float("nan"))])
def test_bad_settings_are_refused(period: float, bandwidth: float) -> None:
    with pytest.raises(ValueError, match="must be"):
        MapPublishSchedule(period, bandwidth)


def test_a_reset_lets_the_next_message_go_at_once() -> None:
    schedule = MapPublishSchedule(2.0, 2.0)
    schedule.published(10.0, 64_000_000)  # 32 s of budget
    assert not schedule.due(20.0)
    schedule.reset()
    assert schedule.due(20.0)
