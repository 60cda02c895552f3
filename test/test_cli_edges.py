"""Bad files and bad flags get one clear line and exit status 2 from every command, never a
traceback: config files that are no parameter files, empty, not UTF-8 or absurd; flags that
contradict each other; outputs that cannot be written; what is not a bag."""
import os
import shutil

import pytest

from soft_arm_model.parameters import default_config_dir

BAD_FILES = {
    "a number where the node's parameters belong": "/**: 5\n",
    "an empty ros__parameters": "/**:\n  ros__parameters:\n",
    "not UTF-8": b"/**:\n  ros__parameters:\n    arm: {a: \"\xff\xfe\"}\n",
    "no node": "arm: [1, 2]\n",
    "a list": "- 1\n- 2\n",
    "broken YAML": "/**:\n  ros__parameters: [\n",
    "numbers where the namespaces belong": "/**:\n  ros__parameters:\n    arm: 5\n    control: 5\n"
                                           "    plant: 5\n    tasks: 5\n    identification: 5\n",
}


def _absurd_arm() -> str:
    text = open(os.path.join(default_config_dir(), "arm.yaml"), encoding="utf-8").read()
    assert "length: 0.38" in text
    return text.replace("length: 0.38", "length: 1e400", 1)


@pytest.fixture(params=sorted(BAD_FILES) + ["an infinite length"])
def bad_file(request, tmp_path):
    text = BAD_FILES.get(request.param) or _absurd_arm()
    path = tmp_path / "bad.yaml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    return str(path)


def _refused(capsys, run, *names):
    """``run()`` exits with status 2 (returned or by SystemExit) and one message naming ``names``."""
    try:
        status = run()
    except SystemExit as exc:
        status = exc.code
    out = capsys.readouterr()
    assert status == 2, (status, out.err[-400:])
    assert "Traceback" not in out.err + out.out
    for name in names:
        assert name in out.err, out.err
    return out.err


def test_the_model_command_names_the_bad_file(capsys, bad_file):
    from soft_arm_model.cli import main
    _refused(capsys, lambda: main(["summary", "--config", bad_file]), bad_file)


def test_the_experiment_refuses_a_bad_arm_or_plant_file_before_anything_runs(capsys, bad_file, tmp_path):
    from soft_arm_experiments.experiment import main
    for flag in ("--arm-file", "--plant-file"):
        _refused(capsys, lambda: main(["triangle", flag, bad_file, "--output", str(tmp_path / "run")]),
                 bad_file)
        assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("name", ["arm", "control", "plant", "tasks"])
def test_the_harness_and_targets_name_a_bad_file_of_the_config_directory(capsys, tmp_path, name):
    from soft_arm_control.targets_cli import main as targets
    from soft_arm_experiments.harness_cli import main as harness
    config = tmp_path / "config"
    shutil.copytree(default_config_dir(), config)
    for text in BAD_FILES.values():
        (config / f"{name}.yaml").write_bytes(text if isinstance(text, bytes) else text.encode())
        path = str(config / f"{name}.yaml")
        _refused(capsys, lambda: harness(["triangle", "--config", str(config), "--quiet"]), path)
        if name != "plant":                                  # soft-arm-targets reads no plant
            _refused(capsys, lambda: targets(["triangle", "--config", str(config)]), path)


def test_identify_names_a_bad_arm_file_and_what_is_not_a_bag(capsys, bad_file, tmp_path):
    from soft_arm_experiments.identify_cli import main
    _refused(capsys, lambda: main([str(tmp_path), "--arm-file", bad_file]), bad_file)
    for bag in (tmp_path, tmp_path / "nothing", bad_file):
        _refused(capsys, lambda: main([str(bag)]), str(bag))
    _refused(capsys, lambda: main([str(tmp_path), "--output", "/proc/forbidden/arm.yaml"]),
             "--output /proc/forbidden")


@pytest.mark.parametrize("name", ["a number where the node's parameters belong", "not UTF-8", "no node",
                                  "broken YAML", "numbers where the namespaces belong"])
def test_a_node_refuses_a_params_file_it_cannot_use_in_one_line(capfd, tmp_path, name):
    """rcl refuses the file (its message, without rcl's source locations), or the node refuses what
    is in it (rclpy's log)."""
    from soft_arm_control.inner_loop_node import main
    path = tmp_path / "bad.yaml"
    text = BAD_FILES[name]
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    assert main(["inner_loop", "--ros-args", "--params-file", str(path)]) == 2
    err = capfd.readouterr().err
    assert "Traceback" not in err and "bad parameter" in err, err
    assert str(path) in err or "is not valid" in err, err
    assert ".c:" not in err


def test_a_value_where_a_namespace_belongs_is_refused_by_the_node(capfd):
    from soft_arm_control.inner_loop_node import main
    assert main(["inner_loop", "--ros-args", "-p", "arm:=5"]) == 2
    err = capfd.readouterr().err
    assert "arm = 5 is not valid: expected the arm.* parameters, not a value" in err


def test_flags_that_contradict_each_other_are_refused(capsys, tmp_path):
    from soft_arm_experiments.experiment import main
    _refused(capsys, lambda: main(["triangle", "--processes", "--emulated-hardware",
                                   "--output", str(tmp_path / "run")]),
             "--emulated-hardware: not allowed with argument --processes")


def test_an_output_that_cannot_be_written_is_refused_before_the_graph_starts(capsys):
    from soft_arm_experiments.experiment import main
    _refused(capsys, lambda: main(["coiling", "--output", "/proc/forbidden/x", "--quiet"]),
             "--output /proc/forbidden/x: cannot write there")


@pytest.mark.parametrize("left", ["metrics.json", "excitation.json"])
def test_an_output_that_holds_an_earlier_result_is_refused(capsys, tmp_path, left):
    """A bring-up that failed before its recorder made bag/ left a result file: a second run there
    would take it for its own (a runner already started, marked valid with the new run's facts)."""
    from soft_arm_experiments.experiment import main
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / left).write_text('{"valid": false}')
    _refused(capsys, lambda: main(["coiling", "--output", str(tmp_path / "run"), "--quiet"]),
             f"already holds a run ({left})")


@pytest.mark.parametrize("complete, interrupted, status, valid", [
    (False, True, 130, False), (False, False, 1, False), (True, True, None, None), (None, False, None, None)])
def test_a_result_written_by_a_runner_stopped_early_is_no_result(tmp_path, complete, interrupted,
                                                                 status, valid):
    """A runner stopped before the end (a Ctrl-C: the composed run's task runner writes the windows
    it played) says so (``complete`` false): the run is marked invalid, and its exit status says
    interrupted (130) or failed (1); a complete one (or one that does not say) is left to be marked
    valid."""
    import json

    from soft_arm_experiments.experiment import _no_result
    path = tmp_path / "metrics.json"
    path.write_text(json.dumps({"task": "triangle", **({} if complete is None else {"complete": complete})}))
    out = {"metrics": str(path), "bag": str(tmp_path / "bag")}
    assert _no_result(out, {"wall_s": 1.0}, None, interrupted, "no metrics written") == status
    data = json.loads(path.read_text())
    assert data.get("valid") is valid
    if valid is False:
        assert data["failure"] == ("interrupted" if interrupted else "stopped") + \
            " before the run played to its end"


def test_no_markers_and_targets_beyond_reach_are_refused_before_anything_moves(capsys, tmp_path):
    from soft_arm_experiments.experiment import main
    from soft_arm_model.cli import main as model
    _refused(capsys, lambda: model(["summary", "--set", "arm.markers.positions=[]"]),
             "arm.markers.positions = [] is not valid")
    far = "tasks.coiling.targets=[5.0, 5.0, 0.0, -0.3, 0.0, -0.3, 0.0, -0.3]"
    _refused(capsys, lambda: main(["coiling", "--set", far, "--accept-closest",
                                   "--output", str(tmp_path / "run")]),
             "tasks.coiling.targets", "target 1: marker4 7.071 m away")


def test_the_campaign_command_names_a_bad_tolerance_file(capsys, bad_file, tmp_path):
    from soft_arm_experiments.campaigns.cli import main
    _refused(capsys, lambda: main(["robustness", "--tolerances", bad_file, "--output", str(tmp_path / "c")]),
             bad_file)
    assert not (tmp_path / "c").exists()


def test_the_campaign_command_refuses_a_folder_without_bags(capsys, tmp_path):
    from soft_arm_experiments.campaigns.cli import main
    (tmp_path / "bags" / "not_a_bag").mkdir(parents=True)
    _refused(capsys, lambda: main(["identification", "--bags", str(tmp_path / "bags"), "--output",
                                   str(tmp_path / "c")]), "no bag folder")
    _refused(capsys, lambda: main(["identification", "--bags", str(tmp_path / "missing"), "--output",
                                   str(tmp_path / "c")]), "not a directory")


def test_a_node_that_failed_on_its_way_out_makes_the_run_no_result():
    """The nodes' exit statuses, kept as they were stopped: a driver whose zero-torque frames did not
    leave exits 1, a node that did not stop within 10 s was killed; either is named, 0 is not."""
    import signal

    from soft_arm_experiments.orchestration import exit_failure
    assert exit_failure({"recorder": 0, "inner_loop": 0}) is None
    assert exit_failure({}) is None
    assert exit_failure({"recorder": 0, "emulated_rig": 1, "clik": -signal.SIGKILL}) == (
        "node emulated_rig exited with status 1; node clik was killed (it did not stop within 10 s)")
