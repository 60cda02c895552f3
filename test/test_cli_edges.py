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
