"""Localhost discovery reaches the first 32 participant ids of a domain: the run checks that its
processes find room there before it starts them."""
import os
import re
import socket
import time
from contextlib import ExitStack, contextmanager

import pytest

from soft_arm_ros.localhost_discovery import REACHED, check_room, discovery_port, taken_participants


def _taking(stack: ExitStack, domain: int, count: int) -> int:
    """Bind plain UDP sockets on the discovery ports of ``domain``'s free participant ids, lowest
    first, until ``count`` of the first :data:`REACHED` are taken (closed with ``stack``); returns
    how many it bound."""
    bound = 0
    for participant in range(REACHED):
        taken = taken_participants(int(domain))
        if len(taken) >= count:
            break
        if participant in taken:
            continue
        sock = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
        sock.bind(("0.0.0.0", discovery_port(int(domain), participant)))
        bound += 1
    return bound


def test_a_participant_takes_the_lowest_free_id_whose_port_the_kernel_lists():
    """The port formula and the kernel's tables as the middleware has them: a participant created
    on the domain adds one id to those taken, the lowest that was free."""
    import gc

    import rclpy
    domain = int(os.environ["ROS_DOMAIN_ID"])
    gc.collect()                            # no participant of an earlier test's nodes left to go
    before = taken_participants(domain)
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("probe", context=context)       # the participant lives with it
        added = taken_participants(domain) - before
        assert added == {min(set(range(REACHED)) - before)}, (before, added)
        node.destroy_node()
        assert taken_participants(domain) == before
    finally:
        rclpy.try_shutdown(context=context)


def _meet(seconds: float) -> bool:
    """Whether two participants created now (two contexts of this process) discover each other's
    node within ``seconds``."""
    import rclpy
    contexts, nodes = [rclpy.Context(), rclpy.Context()], []
    try:
        for k, context in enumerate(contexts):
            rclpy.init(context=context)
            nodes.append(rclpy.create_node(f"participant_{k}", context=context))
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            if ("participant_1", "/") in nodes[0].get_node_names_and_namespaces():
                return True
            time.sleep(0.05)
        return False
    finally:
        for node in nodes:
            node.destroy_node()
        for context in contexts:
            rclpy.try_shutdown(context=context)


def test_past_the_first_32_ids_two_participants_never_meet():
    """The middleware's limit the check is for: with every one of the first 32 ids taken, two new
    participants (ids 32 and 33) do not discover each other; with one of them free (ids 31 and 32)
    they do. (The xdist workers' domains have their discovery ports in the kernel's ephemeral range,
    where a socket of another test may hold one: :func:`_taking` counts what is taken.)"""
    domain = os.environ["ROS_DOMAIN_ID"]
    with ExitStack() as stack:
        _taking(stack, domain, REACHED - 1)
        assert _meet(20.0)
    with ExitStack() as stack:
        _taking(stack, domain, REACHED)
        assert len(taken_participants(int(domain))) == REACHED
        assert not _meet(3.0)


def test_the_room_is_read_from_the_kernels_tables_and_refused_naming_what_it_found(tmp_path):
    """Ports of participants 0, 1 and 5 of domain 7 among others (another domain's, a NatNet
    socket's, an IPv6 one's): three ids taken, 29 free; a run of 29 processes starts, one of 30 is
    refused naming the domain, the count and the remedy (all processes of a run but one need an id
    below 32); another middleware or discovery range is not checked, a domain id that is no number is
    refused."""
    def row(port, address="0100007F"):
        return (f"  1: {address}:{port:04X} 00000000:0000 07 00000000:00000000 00:00000000 00000000"
                "     0        0 12345 2 0000000000000000 0\n")
    header = "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout\n"
    udp, udp6 = tmp_path / "udp", tmp_path / "udp6"
    udp.write_text(header + row(discovery_port(7, 0)) + row(discovery_port(7, 1)) + row(discovery_port(8, 2))
                   + row(1511) + row(discovery_port(7, 0) + 1))
    udp6.write_text(header + row(discovery_port(7, 5), "0" * 32))
    tables = (str(udp), str(udp6), str(tmp_path / "absent"))
    assert taken_participants(7, tables) == {0, 1, 5}
    env = {"ROS_DOMAIN_ID": "7", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    check_room(30, env, tables)
    with pytest.raises(RuntimeError, match=r"ROS domain 7 has 3 of the 32 participant ids that localhost "
                       r"discovery reaches taken on this computer .* this run's 31 processes need 30 of "
                       r"them free: .*or run on another ROS_DOMAIN_ID"):
        check_room(31, env, tables)
    with pytest.raises(RuntimeError, match=r"has 3 of the 32"):
        check_room(31, dict(env, RMW_IMPLEMENTATION=""), tables)            # the default middleware
    check_room(31, dict(env, RMW_IMPLEMENTATION="rmw_cyclonedds_cpp"), tables)
    check_room(31, dict(env, ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET"), tables)
    with pytest.raises(RuntimeError, match=r"ROS_DOMAIN_ID = 'rig' is not a domain id"):
        check_room(2, dict(env, ROS_DOMAIN_ID="rig"), tables)


@contextmanager
def _crowded(taken: int):
    """The test's domain with ``taken`` of its first :data:`REACHED` ids taken, and subprocess.Popen
    a stand-in that starts nothing: yields the domain and the list of what it was asked to start."""
    import subprocess
    started = []
    domain = os.environ["ROS_DOMAIN_ID"]
    with ExitStack() as stack, pytest.MonkeyPatch.context() as patch:
        _taking(stack, domain, taken)
        patch.setattr(subprocess, "Popen", lambda *a, **k: started.append(a))
        yield domain, started


def test_a_run_on_a_domain_without_room_is_refused_before_a_node_starts(tmp_path):
    """soft-arm-experiment's processes mode on a domain whose first 32 ids are all taken: refused at
    once, naming the domain and what it needs, no node process started (where its nodes came up
    unable to meet and the bring-up waited its 60 s)."""
    from soft_arm_experiments import orchestration
    with _crowded(REACHED) as (domain, started):
        begin = time.monotonic()
        with pytest.raises(RuntimeError, match=rf"ROS domain {domain} has 32 of the 32 participant ids "
                           r".* this run's 6 processes need 5 of them free"):
            orchestration.run_processes([], {"bag": str(tmp_path / "bag"),
                                             "metrics": str(tmp_path / "metrics.json")}, task="coiling")
    assert started == [] and time.monotonic() - begin < 30.0           # not the bring-up's 60 s


@pytest.mark.parametrize("mode, taken, processes", [([], REACHED, 2), (["--processes"], REACHED - 5, 7)],
                         ids=["composed", "processes"])
def test_a_live_view_on_a_domain_without_room_is_refused_before_it_starts(tmp_path, capsys, mode, taken,
                                                                          processes):
    """``soft-arm-experiment --live`` on a domain without room for the run and its view: the composed
    run (one process) and its view on a full domain would both take ids localhost discovery does
    not reach and never meet, the view empty and nothing saying why; the processes mode's six
    (five nodes and the orchestrator) and the view, with five ids free, would start the view, then
    refuse the run. Refused at once (status 2), naming the domain and the count, before the view's
    process or the run starts."""
    from soft_arm_experiments.experiment import main
    with _crowded(taken) as (domain, started):
        code = main(["coiling", *mode, "--quiet", "--live", "127.0.0.1:0", "--output", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 2 and started == [], err
    # (another process may bind a port of the domain meanwhile: the count is the kernel's)
    assert re.search(rf"--live 127.0.0.1:0: ROS domain {domain} has \d+ of the 32 participant ids", err), err
    assert f"this run's {processes} processes need {processes - 1} of them free" in err
    assert not (tmp_path / "run" / "bag").exists()


class _Started(Exception):
    """Raised by a stand-in for subprocess.Popen once it has seen what it was to start."""


@pytest.mark.parametrize("mode, range_", [([], "SUBNET"), (["--processes"], "LOCALHOST")],
                         ids=["composed", "processes"])
def test_the_live_view_discovers_on_the_range_of_the_processes_it_meets(tmp_path, monkeypatch, mode,
                                                                        range_):
    """A caller that exported ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET: a composed run's nodes are in the
    caller's process, on its range, and the view starts on that range too; a run of processes starts
    its nodes on localhost discovery, and the view with them (a view on the other range meets a
    process only where one of the two is among the first 32 ids of the other's announcements)."""
    import subprocess

    from soft_arm_experiments.experiment import main
    seen = []

    def popen(*args, **kwargs):
        seen.append(kwargs["env"]["ROS_AUTOMATIC_DISCOVERY_RANGE"])
        raise _Started
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")
    monkeypatch.setattr(subprocess, "Popen", popen)
    with pytest.raises(_Started):
        main(["coiling", *mode, "--quiet", "--live", "127.0.0.1:0", "--output", str(tmp_path / "run")])
    assert seen == [range_]
