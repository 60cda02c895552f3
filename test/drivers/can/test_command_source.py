"""Who may command the motors: the verdict on the publishers of tendon/command."""
from soft_arm_drivers.can.command_source import UNKNOWN_NODE, CommandSource, judge

EXPECTED = "/inner_loop"


def test_the_expected_node_alone_is_accepted():
    verdict = judge([("/", "inner_loop")], EXPECTED, matched=1)
    assert verdict.accepts and verdict.publishers == ("/inner_loop",)
    assert judge([("/lab", "inner_loop")], "/lab/inner_loop", matched=1).accepts


def test_another_node_or_a_second_publisher_is_foreign():
    for publishers, matched in (([("/", "stray")], 1), ([("/", "inner_loop"), ("/", "stray")], 2),
                                ([("/", "inner_loop"), ("/", "inner_loop")], 2),      # a second computer
                                ([("/", "inner_loop")], 2),                         # one the graph lags on
                                ([("/", "stray")], 0),                              # listed, not matched
                                ([("/other", "inner_loop")], 1)):
        verdict = judge(publishers, EXPECTED, matched)
        assert verdict.status == "foreign" and not verdict.accepts, (publishers, matched)
        assert "tendon/command has publishers other than /inner_loop alone" in verdict.describe(EXPECTED)


def test_a_publisher_the_graph_cannot_name_yet_waits():
    assert judge([], EXPECTED, matched=1).status == "unidentified"
    assert judge([("/", UNKNOWN_NODE)], EXPECTED, matched=1).status == "unidentified"
    assert judge([], EXPECTED, matched=0).status == "none"


def test_the_graph_is_asked_again_only_when_the_count_changes_the_verdict_waits_or_ages():
    graph, asked = [[]], []

    def listing():
        asked.append(1)
        return graph[0]
    source = CommandSource(EXPECTED, listing, max_age=0.5)
    assert source.update(1, 0.0).status == "unidentified" and len(asked) == 1
    assert source.update(1, 0.002).status == "unidentified" and len(asked) == 2   # not final: asked again
    graph[0] = [("/", "inner_loop")]
    assert source.update(1, 0.004).accepts and len(asked) == 3
    for k in range(5):
        assert source.update(1, 0.006 + 0.002 * k).accepts
    assert len(asked) == 3                                                     # no graph query per command
    graph[0] = [("/", "inner_loop"), ("/", "stray")]
    assert source.update(2, 0.02).status == "foreign" and len(asked) == 4


def test_a_publisher_replaced_between_two_commands_is_judged_again_on_activation_and_with_age():
    """The inner loop gone and a stray publisher come between two commands: one publisher before and
    after, so the count does not tell. An activation asks the graph whatever was kept, and a kept
    verdict lasts at most max_age of the caller's clock."""
    graph, asked = [[("/", "inner_loop")]], []

    def listing():
        asked.append(1)
        return graph[0]
    source = CommandSource(EXPECTED, listing, max_age=0.5)
    assert source.update(1, 10.0).accepts
    graph[0] = [("/", "_ros2cli_4242")]
    assert source.update(1, 10.1).accepts and len(asked) == 1         # kept: the count is the same
    assert source.update(1, 10.2, fresh=True).status == "foreign"     # an activation asks
    graph[0] = [("/", "inner_loop")]
    assert source.update(1, 10.3).status == "foreign"                 # kept, 0.1 s old
    assert source.update(1, 10.7).accepts and len(asked) == 3         # 0.5 s old: asked again
    graph[0] = [("/", "_ros2cli_4242")]
    assert source.update(1, 11.2).status == "foreign"
