"""The suite's ``change_state`` (test/conftest.py), as a test asks a managed node for a transition:
the node's answer when it comes; when it is lost (the server answered before the middleware
matched the client), the node's state says whether the transition happened."""
from types import SimpleNamespace

from conftest import change_state
from lifecycle_msgs.srv import ChangeState


class _Future:
    def __init__(self, result=None):
        self._result = result

    def done(self) -> bool:
        return self._result is not None

    def result(self):
        return self._result


def _asked(answer, state: str):
    """(executor, client) of a node whose change_state answers ``answer`` (None: lost) and whose
    get_state says ``state``."""
    getter = SimpleNamespace(service_is_ready=lambda: True, call_async=lambda request: _Future(
        SimpleNamespace(current_state=SimpleNamespace(label=state))))
    client = SimpleNamespace(srv_name="/mocap_bridge/change_state", srv_type=ChangeState,
                             service_is_ready=lambda: True,
                             call_async=lambda request: _Future(None if answer is None
                                                                else SimpleNamespace(success=answer)))
    node = SimpleNamespace(clients=[client], created=[], destroyed=[])
    node.create_client = lambda srv_type, name: node.created.append(name) or getter
    node.destroy_client = node.destroyed.append
    executor = SimpleNamespace(spin_once=lambda timeout_sec: None, get_nodes=lambda: [node])
    return executor, client, node


def test_the_answer_is_the_node_s_when_it_comes():
    for answer in (True, False):
        executor, client, node = _asked(answer, "unconfigured")
        assert change_state(executor, client, "activate", timeout=0.05) is answer
        assert node.created == []


def test_a_lost_answer_is_read_from_the_node_s_state():
    executor, client, node = _asked(None, "active")
    assert change_state(executor, client, "activate", timeout=0.05) is True
    assert node.created == ["/mocap_bridge/get_state"] and len(node.destroyed) == 1
    executor, client, _ = _asked(None, "unconfigured")       # refused, and the refusal lost
    assert change_state(executor, client, "activate", timeout=0.05) is False
    executor, client, _ = _asked(None, "inactive")
    assert change_state(executor, client, "configure", timeout=0.05) is True
