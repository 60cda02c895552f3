"""Backlog on a model of rclpy's events executor: an event per message, served in order, each
taking the newest message not yet taken (no callback when there is none). A callback that drains
what arrived while it ran keeps the queue short; nothing is dropped while the callback keeps up."""
import pytest

from soft_arm_ros.backlog import MAX_TAKES, Backlog

MS = 1_000_000       # ns
DISPATCH = 100_000   # ns from an event's service to its callback's start (take, deserialize)
PERIOD = round(1e9 / 240)          # ns, the mocap's


def _serve(backlog, arrivals, cost, drain=True):
    """Serve one event per arrival [ns]; a processed message costs ``cost`` [ns], then (``drain``)
    the callback drains what arrived meanwhile. Returns the arrival times of the messages processed
    and the queue's longest wait [ns] (an event's service minus its arrival)."""
    now, taken, processed, wait = 0, -1, [], 0
    for arrival in arrivals:
        now = max(now, arrival)
        wait = max(wait, now - arrival)
        newest = max(i for i, a in enumerate(arrivals) if a <= now)
        if newest <= taken:
            continue                                  # nothing new to take: no callback
        taken = newest
        now += DISPATCH + cost
        processed.append(arrivals[newest])
        backlog.processed_one()
        if drain:
            def take():
                nonlocal taken
                arrived = max(i for i, a in enumerate(arrivals) if a <= now)
                if arrived <= taken:
                    return None
                taken = arrived                       # a depth-1 queue holds only the newest
                return arrivals[arrived]
            backlog.drain(take)
    return processed, wait


def test_a_callback_that_keeps_up_drops_nothing():
    arrivals = [k * PERIOD for k in range(480)]
    for cost in (1 * MS, PERIOD - DISPATCH - 1):                    # up to the period
        backlog = Backlog()
        processed, wait = _serve(backlog, arrivals, cost)
        assert processed == arrivals and backlog.dropped == 0 and backlog.processed == 480
        assert wait == 0


@pytest.mark.parametrize("cost", [5 * MS, 12.5 * MS, 40 * MS])
def test_a_slow_callback_keeps_the_queue_short(cost):
    """Without draining the queue's wait grows with the run (2 s of frames served at a fraction of
    their rate); drained, at most one callback, and one message processed per callback's worth of
    time plus the wait for the next to arrive; every callback but the last drops what came
    meanwhile."""
    arrivals = [k * PERIOD for k in range(480)]
    _, undrained = _serve(Backlog(), arrivals, cost, drain=False)
    backlog = Backlog()
    processed, wait = _serve(backlog, arrivals, cost)
    assert undrained > 0.3 * 2e9 * (1 - PERIOD / cost)
    assert wait <= DISPATCH + cost
    assert backlog.processed == len(processed) and backlog.dropped >= len(processed) - 1
    assert 2e9 / (cost + DISPATCH + PERIOD) - 1 <= len(processed) <= 2e9 / cost + 1


def test_draining_takes_every_message_there_and_no_more_than_its_bound():
    backlog = Backlog()
    held = ["a", "b"]
    assert backlog.drain(lambda: held.pop(0) if held else None) == "b"
    assert backlog.dropped == 2 and backlog.drain(lambda: None) is None and backlog.dropped == 2
    assert backlog.drain(lambda: "again") == "again" and backlog.dropped == 2 + MAX_TAKES
