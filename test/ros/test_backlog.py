"""BacklogGuard on a model of rclpy's events executor: an event per message, served in order, each
taking the newest message not yet taken. A callback queued behind the last one is dropped; one that
starts on a message's arrival runs; nothing is dropped while the callback keeps up."""
import pytest

from soft_arm_ros.backlog import QUEUED_GAP, BacklogGuard

MS = 1_000_000       # ns
DISPATCH = 100_000   # ns from an event's service to its callback's start (take, deserialize)
DROP = 50_000        # ns a dropped callback takes


def _serve(guard, arrivals, cost):
    """Serve one event per arrival [ns]; a processed message costs ``cost`` [ns]. Returns the
    arrival times of the messages processed and the queue's longest wait [ns] (an event's service
    minus its arrival)."""
    now, taken, processed, wait = 0, -1, [], 0
    for arrival in arrivals:
        now = max(now, arrival)
        wait = max(wait, now - arrival)
        newest = max(i for i, a in enumerate(arrivals) if a <= now)
        if newest <= taken:
            continue                                  # nothing new to take: no callback
        taken = newest
        now += DISPATCH
        if guard.admit(now):
            now += cost
            processed.append(arrivals[newest])
        else:
            now += DROP
        guard.done(now)
    return processed, wait


class _Never(BacklogGuard):
    def admit(self, start):
        super().admit(start)
        return True


PERIOD = round(1e9 / 240)          # ns, the mocap's


def test_a_callback_that_keeps_up_drops_nothing():
    arrivals = [k * PERIOD for k in range(480)]
    for cost in (1 * MS, PERIOD - DISPATCH - QUEUED_GAP - 10_000):       # up to the limit
        guard = BacklogGuard()
        processed, wait = _serve(guard, arrivals, cost)
        assert processed == arrivals and guard.dropped == 0 and guard.processed == 480
        assert wait == 0


@pytest.mark.parametrize("cost", [5 * MS, 12.5 * MS, 40 * MS])
def test_a_slow_callback_keeps_the_queue_short(cost):
    """Without the guard the queue's wait grows with the run (2 s of frames served at a fraction of
    their rate); with it, at most one callback's cost and a period, and one message processed per
    callback's worth of time."""
    arrivals = [k * PERIOD for k in range(480)]
    _, unguarded = _serve(_Never(), arrivals, cost)
    guard = BacklogGuard()
    processed, wait = _serve(guard, arrivals, cost)
    assert unguarded > 0.3 * 2e9 * (1 - PERIOD / cost)
    assert wait <= cost + PERIOD + DISPATCH + DROP
    assert guard.dropped > 0 and guard.processed == len(processed)
    assert 2e9 / (cost + PERIOD + DISPATCH + DROP) - 1 <= len(processed) <= 2e9 / cost + 1


def test_the_gap():
    guard = BacklogGuard(gap=2 * MS)
    assert guard.admit(5 * MS)                    # the first always runs
    guard.done(10 * MS)
    assert not guard.admit(12 * MS - 1)           # queued: dropped
    guard.done(12 * MS)
    assert guard.admit(14 * MS)                   # a gap after the last callback: runs
    assert guard.dropped == 1 and guard.processed == 2
    with pytest.raises(ValueError, match="gap = 0 is not valid"):
        BacklogGuard(gap=0)
