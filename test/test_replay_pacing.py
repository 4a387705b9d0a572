"""The replay pacing rule: recorded gaps divided by the rate, anchored on the first message."""

import threading

import pytest

from mosiv_ros.io.replay import paced


class FakeTime:
    """A clock that only moves when the code under test sleeps (or the test advances it)."""

    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> bool:
        self.sleeps.append(seconds)
        self.now += seconds
        return False


STAMPS = [5_000_000_000, 5_100_000_000, 5_300_000_000, 5_300_000_000, 6_000_000_000]


def replay(rate, fake, **kw):
    out = []
    for stamp in paced(STAMPS, lambda s: s, rate, clock=fake.clock, sleep=fake.sleep, **kw):
        out.append((stamp, fake.now))
    return out


@pytest.mark.parametrize("rate", [1.0, 2.0, 0.5])
def test_messages_are_due_at_recorded_gaps_divided_by_rate(rate):
    fake = FakeTime()
    out = replay(rate, fake)
    assert [s for s, _ in out] == STAMPS
    for stamp, wall in out:
        assert wall - 100.0 == pytest.approx((stamp - STAMPS[0]) * 1e-9 / rate)


def test_rate_zero_replays_without_waiting():
    fake = FakeTime()
    out = replay(0.0, fake)
    assert [s for s, _ in out] == STAMPS and fake.sleeps == []


def test_slow_consumer_does_not_accumulate_drift():
    fake = FakeTime()
    walls = []
    for _ in paced(STAMPS, lambda s: s, 1.0, clock=fake.clock, sleep=fake.sleep):
        walls.append(fake.now)
        fake.now += 0.05  # publishing takes 50 ms
    # Still due at the recorded offsets: the 50 ms are taken out of the following waits.
    assert walls == pytest.approx([100.0, 100.1, 100.3, 100.35, 101.0])


def test_negative_rate_is_rejected_with_its_value():
    with pytest.raises(ValueError, match="-1"):
        list(paced(STAMPS, lambda s: s, -1.0))


def test_stop_ends_the_replay():
    stop = threading.Event()
    fake = FakeTime()
    out = []
    for stamp in paced(STAMPS, lambda s: s, 1.0, stop=stop, clock=fake.clock, sleep=fake.sleep):
        out.append(stamp)
        if len(out) == 2:
            stop.set()
    assert out == STAMPS[:2]
