"""The lockstep simulation's real-time limit: never faster than its factor, no burst to catch up
after falling behind, no wait without a limit; on a fake clock."""
import pytest

from soft_arm_drivers.sim.real_time_limit import RealTimeLimit


class FakeClock:
    """A monotonic clock [s] that moves only when slept on or advanced."""

    def __init__(self):
        self.now, self.slept = 100.0, []

    def __call__(self):
        return self.now

    def sleep(self, seconds):
        self.slept.append(seconds)
        self.now += seconds


def _limited(factor):
    clock = FakeClock()
    return RealTimeLimit(factor, clock, clock.sleep), clock


def test_a_fast_simulation_is_held_to_the_factor():
    """2 ms steps computed in no time: 500 steps (1 s simulated) take 1 s of wall time at factor 1,
    0.5 s at factor 2; the first step anchors the limit."""
    for factor, wall in ((1.0, 1.0), (2.0, 0.5)):
        limit, clock = _limited(factor)
        start = clock.now
        for _ in range(501):
            limit.hold(0.002)
        assert clock.now - start == pytest.approx(wall, rel=1e-9)
        assert clock.slept[0] == pytest.approx(0.002 / factor)


def test_a_simulation_that_fell_behind_goes_on_from_the_wall_clock_without_a_burst():
    """A step that takes 0.5 s of wall time (the plant or the graph slower than real time): the
    steps after it are held as if the simulation had started there, none goes through at once."""
    limit, clock = _limited(1.0)
    limit.hold(0.002)
    clock.now += 0.5                                  # one slow step
    assert limit.hold(0.002) == 0.0
    waits = [limit.hold(0.002) for _ in range(10)]
    assert waits == pytest.approx([0.002] * 10)


def test_a_simulation_slower_than_the_limit_never_waits():
    limit, clock = _limited(1.0)
    for _ in range(20):
        clock.now += 0.003                            # each 2 ms step takes 3 ms
        assert limit.hold(0.002) == 0.0
    assert clock.slept == []


def test_no_limit_never_waits_and_a_bad_factor_is_refused():
    limit, clock = _limited(0.0)
    assert all(limit.hold(0.002) == 0.0 for _ in range(100)) and clock.slept == []
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="real-time factor"):
            RealTimeLimit(bad)
