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


def test_the_graph_is_asked_again_only_when_the_count_changes_or_the_verdict_waits():
    graph, asked = [[]], []

    def listing():
        asked.append(1)
        return graph[0]
    source = CommandSource(EXPECTED, listing)
    assert source.update(1).status == "unidentified" and len(asked) == 1
    assert source.update(1).status == "unidentified" and len(asked) == 2       # not final: asked again
    graph[0] = [("/", "inner_loop")]
    assert source.update(1).accepts and len(asked) == 3
    for _ in range(5):
        assert source.update(1).accepts
    assert len(asked) == 3                                                     # no graph query per command
    graph[0] = [("/", "inner_loop"), ("/", "stray")]
    assert source.update(2).status == "foreign" and len(asked) == 4
