"""The closed loop on the shape estimate (ROS-free harness): with the mocap gone from the start, the
online CLIK on the tendon-only estimate brings the tip to its target, where on the mocap it can
only hold the precomputed reference; the estimate is recorded against the plant's truth."""
import numpy as np
import pytest

from soft_arm_drivers.experiments.harness import load_setup, run_experiment

ONE_TARGET = ["tasks.coiling.phases=[upward]", "tasks.coiling.phase.upward.sequence=[3]",
              "tasks.coiling.phase.upward.window=6.0"]
MOCAP_LOST = ["plant.mocap.occlusion.blackout=[0.0, 1.0e6]"]


@pytest.fixture(scope="module")
def runs():
    return {fb: run_experiment(load_setup("coiling", overrides=ONE_TARGET + MOCAP_LOST, feedback=fb),
                               truth=True)
            for fb in ("mocap", "estimate")}


def test_without_the_mocap_the_estimate_closes_the_loop_and_the_mocap_holds(runs):
    mocap, estimate = runs["mocap"], runs["estimate"]
    assert mocap.goals[0]["status"] == "unseen" and mocap.goals[0]["online_steps"] == 0
    assert estimate.goals[0]["online_steps"] > 500 and estimate.goals[0]["unseen_frames"] == 0
    assert estimate.metrics[0].final_error < 1.5e-3
    assert estimate.metrics[0].final_error < 0.3 * mocap.metrics[0].final_error
    rec = estimate.record.arrays()
    assert not rec["markers_seen"].any()
    error = np.linalg.norm(rec["markers_estimated"][-1] - rec["markers_true"][-1], axis=1)
    assert error[-1] < 3e-3


def test_the_measured_metrics_of_a_run_the_mocap_never_saw_are_an_error():
    short = ["tasks.coiling.phase.upward.window=3.0"]
    setup = load_setup("coiling", overrides=ONE_TARGET + MOCAP_LOST + short)
    with pytest.raises(ValueError, match="frames saw the task's markers"):
        run_experiment(setup)
