"""A lifecycle transition or a runner's start whose answer is lost (the server answered before
discovery matched the client): a transition is judged by the node's state, the bring-up going on
when the node is where the transition leads and failing naming the transition otherwise; a start is
asked again, and the runner's "already started" says the first call took effect."""
import time
from types import SimpleNamespace

import pytest

from soft_arm_experiments import orchestration


class _Node:
    def create_client(self, srv_type, name):
        return SimpleNamespace(srv_name=name)

    def destroy_client(self, client):
        pass


def _lost_answer(state):
    """A ``_call`` whose change_state answer is lost and whose get_state says ``state``."""
    def call(node, client, request, timeout=10.0, checked=True):
        if client.srv_name.endswith("change_state"):
            raise orchestration._NoAnswer(f"service {client.srv_name} did not answer within {timeout:g} s")
        return SimpleNamespace(current_state=SimpleNamespace(label=state))
    return call


def _client():
    from lifecycle_msgs.srv import ChangeState
    return SimpleNamespace(srv_name="/motor_driver/change_state", srv_type=ChangeState)


def test_a_lost_answer_of_a_transition_that_happened_goes_on(monkeypatch, capsys):
    monkeypatch.setattr(orchestration, "_call", _lost_answer("inactive"))
    orchestration._change_state(_Node(), _client(), "configure")
    assert "configure of motor_driver: no answer within 10 s, but motor_driver is inactive" \
        in capsys.readouterr().err


def test_a_lost_answer_of_a_transition_that_did_not_happen_fails(monkeypatch):
    monkeypatch.setattr(orchestration, "_call", _lost_answer("unconfigured"))
    with pytest.raises(RuntimeError, match="configure of motor_driver failed: service "
                                           "/motor_driver/change_state did not answer"):
        orchestration._change_state(_Node(), _client(), "configure")


def _start_answers(*answers):
    """A ``_call`` that gives ``answers`` in turn: None for an answer lost, else (success, message)."""
    answers = list(answers)

    def call(node, client, request, timeout=10.0, checked=True):
        answer = answers.pop(0)
        if answer is None:
            raise orchestration._NoAnswer(f"service {client.srv_name} did not answer within {timeout:g} s")
        if checked and not answer[0]:
            raise RuntimeError(f"{client.srv_name} refused: {answer[1]}")
        return SimpleNamespace(success=answer[0], message=answer[1])
    return call


def test_a_lost_answer_of_a_start_that_happened_goes_on(monkeypatch, capsys):
    from soft_arm_ros.contract import ALREADY_STARTED
    monkeypatch.setattr(orchestration, "_call", _start_answers(None, (False, ALREADY_STARTED)))
    orchestration._start(_Node(), SimpleNamespace(srv_name="/excitation/start"))
    assert "/excitation/start did not answer within 10 s; asked again, it is started" \
        in capsys.readouterr().err


def test_a_lost_answer_of_a_start_that_did_not_arrive_starts_it_on_the_second_call(monkeypatch):
    answers = _start_answers(None, (True, "the identification experiment starts with the next tendon state"))
    monkeypatch.setattr(orchestration, "_call", answers)
    orchestration._start(_Node(), SimpleNamespace(srv_name="/excitation/start"))


def test_a_start_refused_after_a_lost_answer_fails_with_the_refusal(monkeypatch):
    monkeypatch.setattr(orchestration, "_call", _start_answers(None, (False, "no arm loaded")))
    with pytest.raises(RuntimeError, match="/task_runner/start refused: no arm loaded"):
        orchestration._start(_Node(), SimpleNamespace(srv_name="/task_runner/start"))


def test_the_runners_answer_a_second_start_with_what_the_orchestration_looks_for():
    """The runner nodes' ~/start, called twice: the second answer is the contract's ALREADY_STARTED."""
    from soft_arm_experiments.excitation_node import ExcitationNode
    from soft_arm_experiments.task_runner_node import TaskRunnerNode
    from soft_arm_ros.contract import ALREADY_STARTED
    for node_class in (ExcitationNode, TaskRunnerNode):
        runner = SimpleNamespace(started=False, core=SimpleNamespace(task=SimpleNamespace(name="triangle")))
        first = node_class.on_start(runner, None, SimpleNamespace(success=None, message=None))
        second = node_class.on_start(runner, None, SimpleNamespace(success=None, message=None))
        assert first.success and not second.success and second.message == ALREADY_STARTED


def _deactivation(answer):
    """A ``_call`` whose change_state answers ``answer``: None lost (and get_state says active), else
    (success, message)."""
    def call(node, client, request, timeout=10.0, checked=True):
        if client.srv_name.endswith("get_state"):
            return SimpleNamespace(current_state=SimpleNamespace(label="active"))
        if answer is None:
            raise orchestration._NoAnswer(f"service {client.srv_name} did not answer within {timeout:g} s")
        if not answer[0]:
            raise RuntimeError(f"{client.srv_name} refused: {answer[1]}")
        return SimpleNamespace(success=True)
    return call


@pytest.mark.parametrize("answer", [None, (False, "transition not available")])
def test_a_deactivation_refused_or_unanswered_at_the_runs_end_is_a_fault_of_the_run(monkeypatch, answer):
    """Once the motors were enabled, a driver that does not deactivate at the end (a fault the run has
    not heard of, a driver that hangs) leaves the motors' end unknown: a fault of the run, naming the
    transition; after a fault the run recorded (which deactivated the driver) the refusal is expected;
    before the enable, or answered, nothing is recorded."""
    monkeypatch.setattr(orchestration, "_call", _deactivation(answer))

    def watch(enabled: bool, faults=()):
        out = orchestration.DriverFaultWatch()
        out.faults.extend(faults)
        if enabled:
            out.enabled(1.0, time.monotonic() - 0.5)
        return out
    enabled = watch(True)
    orchestration._deactivate_at_end(_Node(), _client(), enabled)
    assert len(enabled.faults) == 1 and enabled.faults[0]["message"].startswith(
        "not deactivated at the run's end: deactivate of motor_driver failed"), enabled.faults
    assert enabled.faults[0]["time_s"] >= 0.5
    recorded = watch(True, [{"message": "stale command", "time_s": 2.0}])
    orchestration._deactivate_at_end(_Node(), _client(), recorded)
    assert recorded.faults == [{"message": "stale command", "time_s": 2.0}]
    before_enable = watch(False)
    orchestration._deactivate_at_end(_Node(), _client(), before_enable)
    assert before_enable.faults == []
    monkeypatch.setattr(orchestration, "_call", _deactivation((True, "")))
    answered = watch(True)
    orchestration._deactivate_at_end(_Node(), _client(), answered)
    assert answered.faults == []


def test_the_drivers_faults_count_from_the_enable_whatever_the_system_clock_does():
    """A status stamped before the enable (the fault the enable cleared) is not the run's; after it a
    fault counts once, timed on the monotonic clock. With the system clock stepped back 5 s after the
    enable, a fault stamped before the enable's time still counts once the active driver has
    reported; and leaving the active state counts only while the task runs."""
    watch = orchestration.DriverFaultWatch()
    assert watch.status(90.0, True, "motor 2 silent", "inactive") is None        # before any enable
    watch.enabled(100.0, time.monotonic())
    assert watch.status(99.9, True, "motor 2 silent", "inactive") is None         # queued from before
    assert watch.faults == []
    stepped = watch.status(95.0, False, "ok", "active")         # the clock stepped back 5 s: armed
    assert stepped is None and watch.faults == []
    fault = watch.status(95.1, True, "watchdog: no command for 0.05 s", "active")
    assert fault == watch.faults[0] and fault["message"].startswith("watchdog")
    assert 0.0 <= fault["time_s"] < 1.0
    assert watch.status(95.2, True, "watchdog: no command for 0.05 s", "inactive") is None   # kept once
    assert watch.status(95.3, False, "ok", "inactive") is None              # not driving: no fault
    watch.driving = True
    left = watch.status(95.4, False, "ok", "inactive")
    assert left["message"] == "left the active state (inactive) while the task ran" and len(watch.faults) == 2
    unarmed = orchestration.DriverFaultWatch()
    unarmed.enabled(100.0, time.monotonic())
    # a fault that deactivates the driver before it reports itself active: its stamp counts
    assert unarmed.status(100.01, True, "motor 1 over temperature", "inactive")["message"] == (
        "motor 1 over temperature")
