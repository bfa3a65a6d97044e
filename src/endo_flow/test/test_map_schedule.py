"""The map's publishing budget: the interval grows with the last message's bytes."""

from __future__ import annotations

import pytest

from endo_flow.map_schedule import MapPublishSchedule


def ticks(schedule: MapPublishSchedule, sizes: list[int], seconds: float, *,
          paused: bool = False, jitter_s: float = 0.0) -> list[float]:
    """Times a timer of the schedule's period publishes at, each message the next size."""
    sent: list[float] = []
    t, k = 0.0, 0
    while t <= seconds:
        now = t - jitter_s if k % 2 else t  # every other tick a hair early
        if schedule.due(now, frames_paused=paused):
            schedule.published(now, sizes[min(len(sent), len(sizes) - 1)])
            sent.append(t)
        t += schedule.period_s
        k += 1
    return sent


def test_small_maps_go_every_period_even_with_early_ticks() -> None:
    schedule = MapPublishSchedule(2.0, 4.0)
    assert ticks(schedule, [1_000_000], 10.0, jitter_s=1e-3) == [0.0, 2.0, 4.0, 6.0, 8.0, 10.0]


def test_a_large_map_waits_its_bytes_over_the_bandwidth() -> None:
    # 24 MB at 4 MB/s: 6 s between messages, a multiple of the 2 s period
    schedule = MapPublishSchedule(2.0, 4.0)
    assert schedule.interval_s(24_000_000) == pytest.approx(6.0)
    assert ticks(schedule, [24_000_000], 20.0, jitter_s=1e-3) == [0.0, 6.0, 12.0, 18.0]
    # the average rate stays within the budget
    sent = ticks(MapPublishSchedule(2.0, 4.0), [24_000_000], 600.0)
    assert 24.0 * (len(sent) - 1) / (sent[-1] - sent[0]) == pytest.approx(4.0)


def test_growing_map_interval_follows_the_last_message() -> None:
    schedule = MapPublishSchedule(1.0, 2.0)
    sent = ticks(schedule, [1_000_000, 4_000_000, 10_000_000, 10_000_000], 30.0)
    # 1 MB -> 1 s (the period), 4 MB -> 2 s, 10 MB -> 5 s
    assert sent[:4] == [0.0, 1.0, 3.0, 8.0]


def test_paused_frames_and_zero_bandwidth_fall_back_to_the_period() -> None:
    assert ticks(MapPublishSchedule(2.0, 1.0), [64_000_000], 6.0, paused=True) == [
        0.0, 2.0, 4.0, 6.0]
    assert ticks(MapPublishSchedule(2.0, 0.0), [64_000_000], 6.0) == [0.0, 2.0, 4.0, 6.0]


@pytest.mark.parametrize(("period", "bandwidth"), [(0.0, 1.0), (-1.0, 1.0), (1.0, -0.5),
                                                   (1.0, float("nan"))])
def test_bad_settings_are_refused(period: float, bandwidth: float) -> None:
    with pytest.raises(ValueError, match="must be"):
        MapPublishSchedule(period, bandwidth)
