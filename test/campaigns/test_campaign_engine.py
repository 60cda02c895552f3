"""The campaign engine on real Dask LocalClusters: records keyed by specification, a dead worker's run
retried elsewhere, a raising run recorded, a resumed campaign running only what is missing."""
import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest

from soft_arm_experiments.campaigns import engine

FUNCTIONS = Path(__file__).with_name("campaign_functions.py")


def function(name: str) -> str:
    return f"{FUNCTIONS}:{name}"


def test_keys_are_canonical_and_tell_specifications_apart():
    a = {"task": "triangle", "plant": {"E": 1.0, "friction": [0.1, 0.2]}, "sets": []}
    same = {"sets": [], "plant": {"friction": [0.1, 0.2], "E": 1.0}, "task": "triangle"}
    assert engine.key_of(a) == engine.key_of(same)
    assert engine.key_of(a) != engine.key_of({**a, "plant": {"E": 1.0, "friction": [0.1, 0.21]}})
    assert engine.key_of(a) != engine.key_of({**a, "sets": ["control.kp=1"]})


def test_a_record_cut_by_a_kill_is_ignored_and_the_rest_read(tmp_path):
    lines = [json.dumps({"key": "a", "status": "ok"}), json.dumps({"key": "b", "status": "ok"})]
    (tmp_path / engine.RECORDS).write_text("\n".join(lines) + "\n" + lines[0][:9], encoding="utf-8")
    assert [r["key"] for r in engine.read_records(tmp_path)] == ["a", "b"]


def test_a_raising_run_is_recorded_as_failed_with_its_error_and_counted(tmp_path):
    specs = [{"x": x} for x in range(4)]
    out = engine.run_campaign(tmp_path, function("raising"), specs, workers=2, warm_up=False)
    assert (out.ran, out.failed, out.interrupted) == (4, 1, False)
    by_x = {r["spec"]["x"]: r for r in out.records}
    assert by_x[2]["status"] == "failed" and by_x[2]["result"] is None
    assert "ValueError: the plant of x = 2 cannot be built" in by_x[2]["error"]
    assert [by_x[x]["result"]["value"] for x in (0, 1, 3)] == [0, 1, 9]
    assert all(by_x[x]["status"] == "ok" for x in (0, 1, 3))
    # kept on disk too, and a restart runs nothing (a failure is a result) unless told to retry
    assert len(engine.read_records(tmp_path)) == 4
    again = engine.run_campaign(tmp_path, function("raising"), specs, workers=1, warm_up=False)
    assert (again.ran, again.failed) == (0, 1)
    retried = engine.run_campaign(tmp_path, function("raising"), specs, workers=1, retry_failed=True,
                                  warm_up=False)
    assert (retried.ran, retried.failed) == (1, 1)
    assert len(retried.records) == 4


def test_workers_load_the_kernels_before_the_first_run_unless_told_the_function_needs_none(tmp_path):
    warmed = engine.run_campaign(tmp_path / "warm", function("kernels_loaded"), [{"x": 0}], workers=1)
    cold = engine.run_campaign(tmp_path / "cold", function("kernels_loaded"), [{"x": 0}], workers=1,
                               warm_up=False)
    assert warmed.records[0]["result"]["loaded"] is True
    assert cold.records[0]["result"]["loaded"] is False


def test_a_restarted_campaign_runs_only_the_missing_specifications(tmp_path):
    first = engine.run_campaign(tmp_path, function("square"), [{"x": x} for x in range(3)], workers=1,
                                warm_up=False)
    assert first.ran == 3
    more = [{"x": x} for x in range(5)]
    second = engine.run_campaign(tmp_path, function("square"), more, workers=1, warm_up=False)
    assert second.ran == 2
    assert [r["spec"]["x"] for r in second.records] == [0, 1, 2, 3, 4]
    assert len(engine.read_records(tmp_path)) == 5


def test_a_folder_of_another_campaign_is_refused(tmp_path):
    engine.run_campaign(tmp_path, function("square"), [{"x": 1}], workers=1, describe={"kind": "sweep"},
                        warm_up=False)
    with pytest.raises(ValueError, match="holds another campaign"):
        engine.run_campaign(tmp_path, function("square"), [{"x": 1}], workers=1,
                            describe={"kind": "robustness"})


def test_a_worker_killed_mid_run_has_its_run_done_elsewhere_and_every_record_arrives(tmp_path):
    marks = tmp_path / "marks"
    marks.mkdir()
    specs = [{"x": x, "dir": str(marks), "sleep": 3.0} for x in range(4)]
    killed = {}

    def kill_the_first_to_start():
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not killed:
            for mark in marks.iterdir():
                x, pid = mark.name.split(".")
                os.kill(int(pid), signal.SIGKILL)
                killed.update(x=int(x), pid=int(pid))
                break
            time.sleep(0.05)

    killer = threading.Thread(target=kill_the_first_to_start)
    killer.start()
    out = engine.run_campaign(tmp_path / "campaign", function("slow"), specs, workers=2, warm_up=False)
    killer.join()
    assert killed, "no run started"
    assert (out.ran, out.failed) == (4, 0)
    assert sorted(r["result"]["value"] for r in out.records) == [0, 1, 4, 9]
    redone = next(r for r in out.records if r["spec"]["x"] == killed["x"])
    assert redone["result"]["pid"] != killed["pid"]
    # the killed run started twice: on the dead worker and on the one that finished it
    assert len(list(marks.glob(f"{killed['x']}.*"))) == 2


def test_overhead_is_the_gap_between_a_workers_runs_plus_the_write():
    records = [{"worker": "a", "started": 0.0, "finished": 1.0, "written_s": 0.001},
               {"worker": "a", "started": 1.05, "finished": 2.0, "written_s": 0.002},
               {"worker": "b", "started": 0.5, "finished": 1.5, "written_s": 0.0}]
    assert engine.overheads(records) == pytest.approx([0.052])
