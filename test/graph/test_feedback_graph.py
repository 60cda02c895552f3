"""The online CLIK on the shape estimate, on the graph: ``--feedback fused`` remaps the clik onto
``fused/markers`` with the shape_estimator node in the graph, and the clik reads the fused tip's
uncertainty on ``fused/tip``: with the tip marker hidden it weighs every frame (never unseen), steps
on the frames whose tip the mocap saw and says why it holds on the others (uncertain), where on the
mocap alone the frames are unseen."""
import json

import pytest

from soft_arm_experiments.experiment import _ros_arguments, run_composed
from soft_arm_experiments.orchestration import FEEDBACK_TOPICS, feedback_arguments, roles
from soft_arm_ros.contract import TOPICS

ONE_TARGET = ["tasks.coiling.phases=[upward]", "tasks.coiling.phase.upward.sequence=[3]",
              "tasks.coiling.phase.upward.window=4.0"]
TIP_HIDDEN = ["plant.mocap.occlusion.bursts.fraction=[0.0, 0.0, 0.0, 0.95]",
              "plant.mocap.occlusion.bursts.duration=0.5"]


def _run(tmp_path, feedback):
    run_dir = tmp_path / feedback
    run_dir.mkdir()
    out = {"bag": str(run_dir / "bag"), "metrics": str(run_dir / "metrics.json")}
    facts = run_composed(_ros_arguments("coiling", ONE_TARGET + TIP_HIDDEN, None), out, task="coiling",
                         feedback=feedback)
    with open(out["metrics"], encoding="utf-8") as fh:
        return facts, json.load(fh)


def test_the_feedback_topics_are_the_contracts_and_add_the_estimator():
    assert FEEDBACK_TOPICS["fused"] == TOPICS["fused"] and FEEDBACK_TOPICS["estimate"] == TOPICS["estimate"]
    assert roles("coiling", "fused")[0] == ("inner_loop", "clik", "shape_estimator")
    assert roles("coiling")[0] == ("inner_loop", "clik") and roles("identification", "fused")[0] == ()
    assert feedback_arguments("estimate") == ["-r", "mocap/markers:=estimate/markers",
                                              "-p", "control.clik.feedback:=estimate"]
    assert feedback_arguments("mocap") == []


@pytest.mark.parametrize("feedback", ["mocap", "fused"])
def test_with_the_tip_hidden_fused_feedback_weighs_every_frame_where_the_mocap_holds(tmp_path, feedback):
    facts, metrics = _run(tmp_path, feedback)
    assert facts["missing_commands"] == 0
    clik = metrics["goals"][0]["clik"]
    # the node's last report (once a second of frame time) of 2 s of online CLIK at 240 Hz
    if feedback == "mocap":
        assert clik["unseen_frames"] > 100 and clik["unseen_frames"] > 5 * clik["online_steps"]
    else:
        # a step on each frame whose tip the mocap saw (a zero covariance on fused/tip: without
        # fused/tip no step is ever taken), none on the estimate's tip, uncertain by centimetres
        assert clik["unseen_frames"] == 0 and clik["uncertain_frames"] > 100 and clik["online_steps"] > 0
        # the status is the report's last frame's: uncertain where it took no step (the tip hidden,
        # 95 % of the time), ok where the mocap saw it on that frame (as on one twin of the plant)
        assert (clik["status"] == "uncertain") == (clik["fraction"] == 0.0), clik
