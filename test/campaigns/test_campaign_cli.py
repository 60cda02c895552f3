"""``soft-arm-campaign`` end to end: real simulations on a real Dask cluster (embedded, or a scheduler
and workers started here on 127.0.0.1), compared with the same runs done serially; Ctrl-C and a
restart; a failing run and its exit status; bad input refused before anything runs."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from threadpoolctl import threadpool_limits

from soft_arm_experiments.campaigns import cli, engine, runs
from soft_arm_experiments.campaigns.plants import (STRUCTURAL_PLANT, draw_plant, load_tolerances,
                                                   plant_overrides)

# a triangle cut to its first vertex, 2 s: a real closed-loop run of about a second
SHORT_TRIANGLE = ["tasks.triangle.phases=[approach]", "tasks.triangle.phase.approach.sequence=[1]",
                  "tasks.triangle.phase.approach.window=2.0", "tasks.triangle.steady_time=1.0"]
WORKSPACE = ["sweep", "--outcome", "workspace", "--levels", "0", "1.5", "3"]


def _sets(values):
    return [a for v in values for a in ("--set", v)]


def _without_times(result):
    """A result without its wall times (``*_s``): what must not depend on where it ran."""
    if isinstance(result, dict):
        return {k: _without_times(v) for k, v in result.items() if not k.endswith("_s")}
    if isinstance(result, list):
        return [_without_times(v) for v in result]
    return result


def _differences(a, b, rel=1e-9, at="result") -> list:
    """Where two results of one run disagree (empty: nowhere): counts, statuses and keys exactly,
    every float to ``rel``. A closed loop done in another process is the same run to its last
    digits only: numpy's vectorised sums start where the array's memory is aligned, which differs
    between processes, and the loop carries the last bit on (1e-10 relative on a 2 s triangle).
    Another plant, seed or setting changes the figures by percent."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{at}: keys {sorted(a)} != {sorted(b)}"]
        return [d for k in a for d in _differences(a[k], b[k], rel, f"{at}[{k!r}]")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{at}: {len(a)} items != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, rel, f"{at}[{i}]")]
    if isinstance(a, float) or isinstance(b, float):
        same = a == pytest.approx(b, rel=rel, abs=1e-12, nan_ok=True)
    else:
        same = a == b
    return [] if same else [f"{at}: {a!r} != {b!r}"]


def _serially(name: str, specs: list) -> list:
    """``runs.<name>`` on each of ``specs`` one after the other in one process, with one BLAS thread
    as a Dask worker has (more threads sum the products of the larger solves in another order: the
    last digits differ, and a closed loop carries them on into its figures)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    code = ("import json, sys\nfrom soft_arm_experiments.campaigns import runs\n"
            f"print(json.dumps([runs.{name}(s) for s in json.load(sys.stdin)]))")
    proc = subprocess.run([sys.executable, "-c", code], input=json.dumps(specs), capture_output=True,
                          text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.splitlines()[-1])


def _task_overrides(spec: dict) -> list:
    """The overrides ``runs.robustness(spec)`` gives its task run and the plant's holding check (they
    must be the same), taken from the calls instead of running them."""
    seen = []

    def spy(task, overrides):
        seen.append(list(overrides))
        return {}
    patch = pytest.MonkeyPatch()
    patch.setattr(runs, "run_task", spy)
    patch.setattr(runs, "plant_holds", spy)
    try:
        runs.robustness(spec)
    finally:
        patch.undo()
    assert len(seen) == 2 and seen[0] == seen[1]
    return seen[0]


def test_two_workers_give_the_records_of_serial_runs_seed_for_seed(tmp_path):
    status = cli.main(WORKSPACE + ["--range", "arm.material.youngs_modulus=1.2e5:1.8e5", "--range",
                                   "arm.material.density=1000:1150", "--samples", "4", "--seed", "7",
                                   "--workers", "2", "--quiet", "--output", str(tmp_path)])
    assert status == 0
    records = engine.read_records(tmp_path)
    assert sorted(r["spec"]["sample"] for r in records) == [0, 1, 2, 3]
    assert len({r["worker"] for r in records}) == 2               # both workers ran
    assert all(r["status"] == "ok" and r["key"] == engine.key_of(r["spec"]) for r in records)
    serial = _serially("sweep", [r["spec"] for r in records])
    assert serial == [r["result"] for r in records]
    # the samples are the seed's: the same seed gives the same specifications, another seed others
    args = cli._parser().parse_args(WORKSPACE + ["--range", "arm.material.youngs_modulus=1.2e5:1.8e5",
                                                 "--range", "arm.material.density=1000:1150", "--samples",
                                                 "4", "--seed", "7", "--output", "x"])
    assert sorted(map(engine.key_of, cli.sweep_specs(args))) == sorted(r["key"] for r in records)
    args.seed = 8
    assert not {engine.key_of(s) for s in cli.sweep_specs(args)} & {r["key"] for r in records}
    summary = json.loads((tmp_path / "summary.json").read_text())
    reach = sorted(r["result"]["reach_m"] for r in records)
    figure = summary["groups"]["workspace"]["figures"]["reach_m"]
    assert figure["worst"] == pytest.approx(reach[0]) and figure["best"] == pytest.approx(reach[-1])
    assert figure["median"] == pytest.approx((reach[1] + reach[2]) / 2)
    assert list(tmp_path.glob("histograms-*.png"))


def test_a_robustness_campaign_runs_the_task_on_the_draws_of_its_seeds(tmp_path):
    status = cli.main(["robustness", "--draws", "1", "--seed", "12", "--no-structural", "--tasks", "triangle",
                       "--workers", "1", "--quiet", "--output", str(tmp_path)] + _sets(SHORT_TRIANGLE))
    assert status == 0
    [record] = engine.read_records(tmp_path)
    assert record["spec"]["plant"] == draw_plant(12, load_tolerances())
    result = record["result"]
    assert result["simulated_s"] == pytest.approx(2.0) and result["transitions"] == 1
    # the plant's holding checked on the one target the run visits
    assert isinstance(result["plant_holds"], bool) and result["plant_targets"] == [1]
    assert len(result["plant_margins"]) == 1
    # the recorded run is the drawn plant's (its overrides, as runs.robustness hands them on), and
    # the same run done here, serially, gives the recorded result (the plant's own holding check,
    # some seconds of equilibria, is left out of the repetition: the overrides show it is the same)
    overrides = _task_overrides(record["spec"])
    drawn = plant_overrides(draw_plant(12, load_tolerances()))
    assert overrides[:len(drawn)] == drawn
    with threadpool_limits(1):                  # one BLAS thread, as the worker's (_serially)
        serial = runs.run_task(record["spec"]["task"], overrides)
    assert not _differences(_without_times(serial), _without_times({k: result[k] for k in serial}))
    summary = json.loads((tmp_path / "summary.json").read_text())
    figure = summary["groups"]["triangle, all draws"]["figures"]["rms_mm"]
    assert figure["median"] == figure["worst"] == pytest.approx(result["rms_mm"])
    assert "| steady-state RMS task error [mm] |" in (tmp_path / "summary.md").read_text()


def test_draws_are_their_seeds_own_whatever_else_the_campaign_holds():
    parse = cli._parser().parse_args
    wide = cli.robustness_specs(parse(["robustness", "--draws", "4", "--seed", "11", "--output", "x"]))
    one = cli.robustness_specs(parse(["robustness", "--draws", "1", "--seed", "12", "--no-structural",
                                      "--output", "x"]))
    assert {engine.key_of(s) for s in one} <= {engine.key_of(s) for s in wide}
    assert [s["draw"] for s in wide[::2]] == ["structural", 11, 12, 13, 14]
    assert wide[0]["plant"] == STRUCTURAL_PLANT
    assert len({json.dumps(s["plant"], sort_keys=True) for s in wide}) == 5


def _campaign(args, **kwargs):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "soft_arm_experiments.campaigns.cli"] + args, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs)


def test_ctrl_c_keeps_what_finished_and_the_restart_runs_only_the_rest(tmp_path):
    moduli = "[1.2e5,1.4e5,1.6e5,1.8e5]"
    # runs of 8^4 = 4096 equilibria (1.6 s each on this project's machine; 4^4 took 0.12 s, all four
    # done before the signal landed) on two workers: the signal lands at the first record, while the
    # third and fourth run
    levels = ["0", "0.4", "0.8", "1.2", "1.6", "2.0", "2.4", "2.8"]
    args = ["sweep", "--outcome", "workspace", "--levels", *levels,
            "--vary", f"arm.material.youngs_modulus={moduli}", "--workers", "2", "--output", str(tmp_path)]
    # a terminal's Ctrl-C goes to the whole process group: the command and its cluster's workers,
    # started with SIGINT at its default whatever this process inherited (a shell's background job
    # ignores it, and Python then never turns it into KeyboardInterrupt)
    proc = _campaign(args, start_new_session=True,
                     preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(engine.read_records(tmp_path)) < 1:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted; run the same command again" in err
    kept = engine.read_records(tmp_path)
    assert 1 <= len(kept) < 4
    proc = _campaign(args)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert f"4/4 runs recorded ({4 - len(kept)} now, {len(kept)} before), 0 failed" in err
    records = engine.read_records(tmp_path)
    assert len(records) == 4 and len({r["key"] for r in records}) == 4
    assert [r["key"] for r in records[:len(kept)]] == [r["key"] for r in kept]


def test_a_run_that_fails_is_recorded_with_its_error_and_the_exit_status_says_so(tmp_path):
    # the second sample's first vertex is above the base plane, where no arm hanging from it reaches
    far = [-0.033, 0.099, 0.05, 0.031, -0.030, 0.138, -0.241, 0.056, 0.048, 0.123, -0.282, 0.043]
    good = [-0.033, 0.099, -0.326, 0.031, -0.030, 0.138, -0.241, 0.056, 0.048, 0.123, -0.282, 0.043]
    status = cli.main(["sweep", "--outcome", "triangle", "--vary", f"tasks.triangle.targets={[good, far]}",
                       "--workers", "1", "--quiet", "--output", str(tmp_path)] + _sets(SHORT_TRIANGLE))
    assert status == 1
    records = engine.read_records(tmp_path)
    assert [r["status"] for r in records] == ["ok", "failed"]
    assert "TargetError" in records[1]["error"] and records[1]["result"] is None
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["failed"] == 1 and summary["groups"]["triangle"]["failed"] == 1
    assert "TargetError" in summary["failures"][0]["error"]
    assert "## Failed runs" in (tmp_path / "summary.md").read_text()


@pytest.fixture
def dask_cluster(tmp_path):
    """A scheduler and two one-thread workers, each a process of its own, on 127.0.0.1."""
    dask = str(Path(sys.executable).with_name("dask"))
    scheduler_file = tmp_path / "scheduler.json"
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(scheduler_file)], stderr=subprocess.DEVNULL)]
    try:
        deadline = time.monotonic() + 60
        while not scheduler_file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        for _ in range(2):
            procs.append(subprocess.Popen([dask, "worker", "--scheduler-file", str(scheduler_file), "--host",
                                           "127.0.0.1", "--nthreads", "1", "--no-dashboard"],
                                          stderr=subprocess.DEVNULL))
        address = json.loads(scheduler_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        yield address, [p.pid for p in procs[1:]]
    finally:
        for proc in procs[::-1]:
            proc.send_signal(signal.SIGINT)
        for proc in procs[::-1]:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()


def _parent(pid: int) -> int:
    with open(f"/proc/{pid}/status", encoding="ascii") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith("PPid:"))


def test_a_campaign_runs_on_an_existing_cluster_given_its_scheduler(tmp_path, dask_cluster):
    address, cluster_pids = dask_cluster
    out = tmp_path / "campaign"
    offsets = "[[0.5,0.5,0.5,0.5],[0.6,0.6,0.6,0.6],[0.7,0.7,0.7,0.7],[0.65,0.55,0.65,0.55]]"
    status = cli.main(WORKSPACE + ["--levels", "0", "1", "2", "3", "--vary",
                                   f"arm.tendons.offset_fraction={offsets}",
                                   "--scheduler", address, "--quiet", "--output", str(out)])
    assert status == 0
    records = engine.read_records(out)
    assert len(records) == 4
    # every run on the cluster's workers (each a process under a worker the fixture started), none
    # here; how the scheduler shares them out is its own (a worker that registers late gets none)
    pids = {int(r["worker"].rpartition(":")[2]) for r in records}
    assert os.getpid() not in pids
    assert all(pid in cluster_pids or _parent(pid) in cluster_pids for pid in pids), (pids, cluster_pids)
    assert _serially("sweep", [r["spec"] for r in records[:2]]) == [r["result"] for r in records[:2]]
    # a wider offset reaches farther from the axis
    reach = {r["spec"]["sets"][0].partition("=")[2]: r["result"]["reach_m"] for r in records}
    assert reach["[0.7, 0.7, 0.7, 0.7]"] > reach["[0.5, 0.5, 0.5, 0.5]"]


@pytest.mark.parametrize("args, message", [
    (["robustness", "--draws", "-1"], "--draws -1: expected 0 or more"),
    (["robustness", "--draws", "0", "--no-structural"], "nothing to run"),
    (["robustness", "--tasks", "no_such_task"], "no_such_task"),
    (["robustness", "--set", "control.no_such_key=1"], "no_such_key"),
    (["robustness", "--workers", "0"], "--workers 0: expected at least 1"),
    (["robustness", "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "--scheduler and --workers"),
    (["sweep"], "give --vary (a grid) or --range"),
    (["sweep", "--vary", "arm.material.youngs_modulus=1e5"], "expected KEY=[value, value, ...]"),
    (["sweep", "--range", "arm.material.youngs_modulus=2e5:1e5"], "LOW <= HIGH"),
    (["sweep", "--vary", "arm.material.youngs_modulus=[-1]"], "arm.material.youngs_modulus"),
    (["sweep", "--vary", "arm.material.youngs_modulus=[1e5]", "--levels", "-1"], "tensions must be >= 0"),
])
def test_bad_input_is_refused_with_the_key_before_anything_runs(tmp_path, capsys, args, message):
    assert cli.main(args + ["--output", str(tmp_path / "c")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "c" / engine.RECORDS).exists()


def test_a_tolerance_file_with_a_bad_value_is_refused_naming_its_key(tmp_path, capsys):
    bad = tmp_path / "tolerances.yaml"
    text = (Path(__file__).parents[2] / "config" / "campaign.yaml").read_text(encoding="utf-8")
    assert "youngs_modulus_scale: [0.8, 1.2]" in text
    bad.write_text(text.replace("youngs_modulus_scale: [0.8, 1.2]", "youngs_modulus_scale: [1.2, 0.8]"),
                   encoding="utf-8")
    assert cli.main(["robustness", "--tolerances", str(bad), "--output", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "campaign.tolerances.youngs_modulus_scale" in err and "[low, high]" in err


def test_an_unwritable_output_and_another_campaigns_folder_are_refused(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    args = WORKSPACE + ["--vary", "arm.material.youngs_modulus=[1.5e5]", "--quiet", "--workers", "1"]
    assert cli.main(args + ["--output", str(blocker / "c")]) == 2
    assert "cannot write there" in capsys.readouterr().err
    (tmp_path / "c").mkdir()
    engine._check_campaign(tmp_path / "c", {"function": "x:y", "kind": "robustness"})
    assert cli.main(args + ["--output", str(tmp_path / "c")]) == 2
    assert "holds another campaign" in capsys.readouterr().err


def test_the_progress_bar_shows_done_running_failed_the_eta_and_the_dashboard_once():
    import io
    stream = io.StringIO()
    bar = cli.ProgressBar(stream)
    state = {"done": 3, "total": 12, "running": 2, "failed": 1, "eta_s": 3725.0,
             "dashboard": "http://127.0.0.1:8787/status"}
    bar(state)
    bar({**state, "done": 12, "running": 0, "eta_s": 0.0})
    text = stream.getvalue()
    assert text.count("dashboard http://127.0.0.1:8787/status") == 1
    assert "3/12 done, 2 running, 1 failed, ETA 1:02:05" in text
    assert "[" + "#" * 7 + "." * 23 + "]" in text and "[" + "#" * 30 + "]" in text
    assert text.endswith("\n")
