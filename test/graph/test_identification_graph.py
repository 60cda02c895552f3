"""The identification experiment as a graph run (composed and one process per node) and
soft-arm-identify on its bag: what a user runs, end to end."""
import json
import os
import pathlib

import pytest

from conftest import node_logs
from soft_arm_experiments.experiment import main as experiment
from soft_arm_experiments.identify_cli import main as identify
from soft_arm_drivers.mocap.bridge_config import load_mocap_config
from soft_arm_model import load_arm_config
from soft_arm_model.parameters import read_parameters

# a short experiment: one level, one pair, 3 s plateaus, one short chirp (24 s simulated)
SHORT = ["identification.steps=1", "identification.pairs=[1,2]", "identification.hold=3.0",
         "identification.average=1.0", "identification.step.hold=1.0", "identification.chirp.duration=2.0",
         "identification.chirp.tendons=[3]"]
# the fit of that bag, without the basis check (what it adds is tested in test_identification_run.py)
FIT = ["identification.fit.min_plateau=2.5", "identification.average=1.0",
       "identification.fit.legendre_order=[3,0]", "identification.fit.shear=false",
       "identification.fit.basis_check.max_evaluations=0"]


def _sets(pairs):
    return [a for p in pairs for a in ("--set", p)]


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("identification") / "run"
    assert experiment(["identification", "--quiet", "--output", str(out)] + _sets(SHORT)) == 0
    return out


def test_the_experiment_records_a_bag_and_its_schedule(short_run):
    with open(short_run / "excitation.json", encoding="utf-8") as fh:
        schedule = json.load(fh)
    assert schedule["valid"] and schedule["task"] == "identification"
    assert [s["kind"] for s in schedule["segments"]].count("chirp") == 1
    assert (short_run / "bag" / "metadata.yaml").is_file()


def test_identify_writes_an_arm_every_entry_point_takes(short_run, tmp_path, capsys):
    arm_file, figures = tmp_path / "arm.yaml", tmp_path / "figures"
    code = identify([str(short_run / "bag"), "--output", str(arm_file), "--json", "--plot", str(figures)]
                    + _sets(FIT))
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert report["plateaus"] == 16 and report["dynamic_segments"] == 5
    assert report["dynamic"]["rotor_mass"]["value"] > 0 and len(report["marker_rms"]) == 4
    arm = load_arm_config(str(arm_file))
    assert abs(arm.material.youngs_modulus / 1.5e5 - 1.15) < 0.1          # plant.yaml: E x1.15
    calibration = read_parameters(str(arm_file))["rig"]["mocap"]["calibration"]   # over mocap.yaml
    bridge = load_mocap_config(overrides={f"mocap.calibration.{k}": v for k, v in calibration.items()})
    assert bridge.calibration.rotation.shape == (3, 3)
    assert sorted(p.name for p in figures.iterdir()) == [
        "dynamics.png", "hysteresis.png", "markers.png", "shortenings.png"]


def test_a_bag_without_the_commands_is_refused_naming_the_topic(short_run, tmp_path, capsys):
    """The run's bag copied without its tendon/command messages (a recorder not told to keep them)."""
    from soft_arm_drivers.recording.rosbag_writer import RosbagWriter, TopicSpec
    from rosbags.highlevel import AnyReader
    with AnyReader([short_run / "bag"]) as reader:
        kept = [c for c in reader.connections if c.topic != "/tendon/command"]
        with RosbagWriter(tmp_path / "bag", [TopicSpec(c.topic, c.msgtype) for c in kept]) as writer:
            for connection, stamp, raw in reader.messages(connections=kept):
                writer.write(connection.topic, stamp, raw)
    assert identify([str(tmp_path / "bag")] + _sets(FIT)) == 2
    assert "the bag lacks tendon/command" in capsys.readouterr().err


def test_a_bag_whose_run_is_marked_invalid_is_refused(short_run, tmp_path, capsys):
    """The same bag beside an excitation.json that says the run faulted: no fit."""
    import shutil
    run = tmp_path / "faulted"
    shutil.copytree(short_run / "bag", run / "bag")
    with open(short_run / "excitation.json", encoding="utf-8") as fh:
        schedule = json.load(fh)
    schedule.update(valid=False, failure="the motor driver faulted: stale command")
    with open(run / "excitation.json", "w", encoding="utf-8") as fh:
        json.dump(schedule, fh)
    assert identify([str(run / "bag")] + _sets(FIT)) == 2
    err = capsys.readouterr().err
    assert "marked invalid" in err and "stale command" in err


def test_a_campaign_fits_every_bag_of_a_folder_and_records_the_one_refused(short_run, tmp_path):
    """``soft-arm-campaign identification --bags``: the run's folder, and a copy marked invalid."""
    import shutil
    from soft_arm_experiments.campaigns.cli import main as campaign
    from soft_arm_experiments.campaigns.engine import read_records
    bags = tmp_path / "bags"
    shutil.copytree(short_run, bags / "good")
    shutil.copytree(short_run, bags / "faulted")
    schedule = json.loads((bags / "faulted" / "excitation.json").read_text(encoding="utf-8"))
    schedule.update(valid=False, failure="the motor driver faulted: stale command")
    (bags / "faulted" / "excitation.json").write_text(json.dumps(schedule), encoding="utf-8")
    out = tmp_path / "campaign"
    assert campaign(["identification", "--bags", str(bags), "--workers", "1", "--quiet", "--output", str(out)]
                    + _sets(FIT)) == 1
    records = {pathlib.Path(r["spec"]["bag"]).parent.name: r for r in read_records(out)}
    assert records["faulted"]["status"] == "failed" and "marked invalid" in records["faulted"]["error"]
    good = records["good"]
    assert good["status"] == "ok", good["error"]
    estimate = good["result"]["estimates"]["youngs_modulus"]
    assert abs(estimate["value"] / 1.5e5 - 1.15) < 0.1 and estimate["standard_error"] > 0
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["groups"]["bags"]["runs"] == 2 and summary["groups"]["bags"]["failed"] == 1


def test_the_identification_experiment_runs_one_process_per_node(tmp_path, monkeypatch):
    """The experiment plays to its end, and each node logs from a process of its own (its own ROS
    log file, named with its process id, not this one's)."""
    monkeypatch.setenv("ROS_LOG_DIR", str(tmp_path / "log"))          # the node processes inherit it
    out = tmp_path / "procs"
    # half the plateaus and steps of SHORT (27 s simulated): what is checked is where the nodes ran;
    # the plant not held to real time (the excitation commands it in the lock, and no controller
    # outside the lock needs the rig's time budget)
    shorter = SHORT + ["identification.hold=1.5", "identification.average=0.5",
                       "identification.step.hold=0.5", "identification.chirp.duration=1.0",
                       "graph.simulator.max_real_time_factor=0"]
    assert experiment(["identification", "--processes", "--quiet", "--output", str(out)]
                      + _sets(shorter)) == 0
    with open(out / "excitation.json", encoding="utf-8") as fh:
        played = json.load(fh)
    assert played["valid"] and played["duration"] == 27.0, played
    logs = node_logs(tmp_path / "log")
    nodes = ("simulator", "excitation", "recorder")
    assert all(len(logs.get(name, [])) == 1 for name in nodes), logs
    pids = [logs[name][0] for name in nodes]
    assert len(set(pids)) == len(nodes) and os.getpid() not in pids, logs


def test_calibrate_identifies_then_reruns_the_task_with_the_identified_arm(tmp_path):
    """One command: the experiment, the fit and a (short) triangle whose controller's model is the
    identified arm, while the plant stays plant.yaml over arm.yaml (written beside the run)."""
    from soft_arm_experiments.harness import load_setup
    short_triangle = ["tasks.triangle.phases=[approach]", "tasks.triangle.phase.approach.window=3.0",
                      "tasks.triangle.phase.approach.sequence=[1]", "control.clik.switch_delay=1.0"]
    out = tmp_path / "calibrate"
    sets = _sets(SHORT + FIT + short_triangle)
    assert experiment(["calibrate", "--quiet", "--output", str(out)] + sets) == 0
    identified = load_arm_config(str(out / "arm_identified.yaml"))
    with open(out / "triangle" / "metrics.json", encoding="utf-8") as fh:
        metrics = json.load(fh)
    assert metrics["summary"]["transitions"] == 1
    plant = load_arm_config(str(out / "triangle" / "plant_arm.yaml"))
    setup = load_setup("triangle")
    assert plant == setup.plant.plant_arm(setup.arm)
    assert abs(identified.material.youngs_modulus / plant.material.youngs_modulus - 1) < 0.05
    assert (out / "identification" / "fit" / "markers.png").is_file()


def test_calibrate_serves_each_of_its_runs_live_where_asked(tmp_path, monkeypatch):
    """``calibrate --live`` passes the address on to its runs (each serves its own view, counted in
    the domain's room), where it was dropped."""
    from soft_arm_experiments import experiment as module
    calls = []
    monkeypatch.setattr(module, "main", lambda argv: calls.append(argv) or 3)    # the runs, stood in for
    assert experiment(["calibrate", "--live", "127.0.0.1:0", "--output", str(tmp_path / "c")]) == 3
    argv, = calls
    assert argv[0] == "identification" and argv[argv.index("--live") + 1] == "127.0.0.1:0"


def test_calibrate_refuses_to_rerun_anything_but_a_task(tmp_path, capsys):
    assert experiment(["calibrate", "--rerun", "calibrate", "--output", str(tmp_path / "c")]) == 2
    assert "--rerun calibrate is not valid" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()
