"""A lifecycle transition whose answer is lost (the server answered before discovery matched the
client) is judged by the node's state: the bring-up goes on when the node is where the transition
leads, and fails naming the transition otherwise."""
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
