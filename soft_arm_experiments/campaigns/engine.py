"""A campaign's runs on Dask distributed: keyed, resumable, honest about failures, with progress.

A campaign is a folder and a list of run specifications (JSON-ready dicts), each run one call of
``function(spec)`` on a worker. Every run is keyed by its specification (the SHA-256 of its
canonical JSON): ``records.jsonl`` in the folder holds one line per finished run, written and
flushed as it arrives, so a campaign restarted on its folder runs only the keys it lacks, and a
campaign interrupted (Ctrl-C, a kill) loses at most the runs in flight.

The runs go to a Dask cluster: by default an embedded ``LocalCluster`` of ``workers`` processes
(one thread each: the runs are CPU-bound Python and numba) on 127.0.0.1; with ``scheduler`` an
existing cluster's scheduler address (``tcp://host:8786``), to which a lab adds machines with
``dask worker tcp://host:8786``. A worker that dies mid-run has its run given to another
(Dask's own rescheduling); a run that raises is recorded as failed with its error (the run
functions catch everything, so that one bad plant does not end the campaign), and counted.

Per worker, what every run needs (the compiled kernels, the controller's actuation map) is built
once: the workers import the package and warm the kernels when they start (:class:`WarmUp`), and
fitted actuation maps are kept across processes
(:func:`soft_arm_control.actuation_map.cached_fit`).
"""
from __future__ import annotations

import hashlib
import importlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Optional

from distributed.diagnostics.plugin import WorkerPlugin

RECORDS = "records.jsonl"
CAMPAIGN = "campaign.json"


def canonical(spec: dict) -> str:
    """A specification as canonical JSON (sorted keys, no spaces): what its key is made of."""
    return json.dumps(spec, sort_keys=True, separators=(",", ":"))


def key_of(spec: dict) -> str:
    """The run's key: the first 24 hex digits of the SHA-256 of its canonical specification."""
    return hashlib.sha256(canonical(spec).encode()).hexdigest()[:24]


def load_function(path: str) -> Callable:
    """``package.module:function``, imported; ``path/to/file.py:function`` too (a bench script),
    with the file's folder on the import path."""
    module_name, _, name = path.partition(":")
    if module_name.endswith(".py"):
        folder, module_name = os.path.split(os.path.abspath(module_name))
        if folder not in sys.path:
            sys.path.insert(0, folder)
        module_name = module_name[:-3]
    return getattr(importlib.import_module(module_name), name)


def read_records(folder: Path) -> list:
    """The records of ``folder``, in the order written; a last line cut off by a kill is ignored."""
    path = Path(folder) / RECORDS
    if not path.exists():
        return []
    out = []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            try:
                out.append(json.loads(line))
            except ValueError:
                continue                              # a line the last writer did not finish
    return out


class WarmUp(WorkerPlugin):
    """Dask worker plugin: import the package and compile (or load) the kernels when a worker
    starts, so that no run pays for it; a worker added to the cluster later does the same."""

    name = "soft-arm-warm-up"

    def setup(self, worker):
        from soft_arm_experiments.warmup import STEPS
        for _, step in STEPS:
            step()


@dataclass
class Outcome:
    """What a campaign did: the records of the campaign's specifications in their order (finished
    earlier or now), how many ran now, how many of the records failed, whether it was interrupted,
    the wall time [s] of this call, the workers' number, and the overhead per run [s] (the workers'
    gaps between runs and the writing of the records: :func:`overheads`)."""
    records: list
    ran: int
    failed: int
    interrupted: bool
    wall_s: float
    workers: int
    overhead_s: list = field(default_factory=list)


def run_campaign(folder, function: str, specs: Iterable[dict], *, scheduler: Optional[str] = None,
                 workers: Optional[int] = None, describe: Optional[dict] = None,
                 progress: Optional[Callable[[dict], None]] = None, upload: Iterable[str] = (),
                 retry_failed: bool = False, warm_up: bool = True) -> Outcome:
    """Run ``function`` (``module:name``) on every specification of ``specs`` that ``folder`` has no
    record of yet, on a new ``LocalCluster`` of ``workers`` processes (default: the cores) or on
    the cluster of ``scheduler``; append each record to ``folder/records.jsonl`` as it arrives.
    ``describe``: what the campaign is (written to ``campaign.json`` once; a folder of another
    campaign is refused with ValueError). ``progress(state)`` is called when the runs are submitted
    and when one finishes, at most once a second and always at the last (``done``, ``failed``,
    ``running``, ``pending``, ``total``, ``eta_s``, ``dashboard``). ``upload``:
    files the workers import ``function`` from (a bench script). ``retry_failed``: run again the
    specifications whose record says failed (the last record of a key is the one that counts).
    ``warm_up``: every worker loads the package's compiled kernels when it starts (:class:`WarmUp`,
    some 2 s of CPU each), so that no run's time includes them; False for a ``function`` that calls
    none of them. Ctrl-C stops it: the runs in flight
    are cancelled, everything finished is kept (``interrupted``)."""
    from distributed import Client, LocalCluster, as_completed

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _check_campaign(folder, {"function": function, **(describe or {})})
    specs = list(specs)
    keyed = {key_of(spec): spec for spec in specs}
    finished = {r["key"]: r for r in read_records(folder) if r["key"] in keyed}
    if retry_failed:
        finished = {key: r for key, r in finished.items() if r["status"] == "ok"}
    todo = [(key, spec) for key, spec in keyed.items() if key not in finished]
    start = time.monotonic()
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1,
                               processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0",
                               silence_logs=40)
    client = Client(scheduler or cluster)
    interrupted, ran, written, n_workers = False, 0, [], 0
    try:
        for path in upload:
            client.upload_file(path)
        if warm_up:
            client.register_plugin(WarmUp())
        n_workers = max(1, len(client.scheduler_info()["workers"]))
        futures = {client.submit(_run, function, spec, key=f"soft-arm-{key}", pure=False): key
                   for key, spec in todo}
        state = {"done": len(finished), "failed": sum(r["status"] != "ok" for r in finished.values()),
                 "running": min(len(todo), n_workers), "pending": len(todo),
                 "total": len(keyed), "eta_s": math.nan, "dashboard": client.dashboard_link,
                 "run_s": []}
        if progress is not None:
            progress(dict(state))
        last_report = time.monotonic()
        with open(folder / RECORDS, "a", encoding="utf-8") as out:
            pending = as_completed(futures, with_results=False)
            for future in pending:
                key = futures[future]
                record = _result_of(future, keyed[key], key)
                t0 = time.perf_counter()
                out.write(json.dumps(record) + "\n")
                out.flush()
                os.fsync(out.fileno())
                record["written_s"] = time.perf_counter() - t0
                written.append(record)
                ran += 1
                state["done"] += 1
                state["failed"] += record["status"] != "ok"
                state["pending"] = len(todo) - ran
                state["running"] = min(state["pending"], n_workers)
                state["run_s"].append(record.get("run_s", 0.0))
                mean = sum(state["run_s"]) / len(state["run_s"])
                state["eta_s"] = mean * math.ceil(state["pending"] / n_workers)
                if progress is not None and (time.monotonic() - last_report > 1.0 or state["pending"] == 0):
                    progress(dict(state))
                    last_report = time.monotonic()
    except KeyboardInterrupt:
        interrupted = True
    finally:
        try:
            client.close()
        finally:
            if cluster is not None:
                cluster.close()
    by_key = {r["key"]: r for r in read_records(folder)}
    records = [by_key[key] for key in keyed if key in by_key]
    failed = sum(r["status"] != "ok" for r in records)
    return Outcome(records, ran, failed, interrupted, time.monotonic() - start, n_workers,
                   overheads(written))


def _check_campaign(folder: Path, describe: dict):
    """Write ``campaign.json`` the first time; refuse a folder that holds another campaign."""
    path = folder / CAMPAIGN
    if path.exists():
        existing = json.loads(path.read_text(encoding="utf-8"))
        if existing != json.loads(json.dumps(describe)):
            raise ValueError(f"{folder} holds another campaign ({path}: {existing}); give a new folder")
        return
    path.write_text(json.dumps(describe, indent=2, sort_keys=True) + "\n", encoding="utf-8")


def _run(function: str, spec: dict) -> dict:
    """On a worker: one run, timed, with where it ran; an exception becomes a failed record."""
    import socket
    import traceback
    started = time.time()
    t0 = time.perf_counter()
    try:
        result = load_function(function)(spec)
        status, error = "ok", None
    except Exception as exc:  # noqa: BLE001 - a run that raises is a record, not the campaign's end
        result, status = None, "failed"
        error = f"{type(exc).__name__}: {exc}\n" + "".join(traceback.format_exc().splitlines(True)[-6:])
    return {"status": status, "error": error, "result": result, "run_s": time.perf_counter() - t0,
            "started": started, "finished": time.time(), "worker": f"{socket.gethostname()}:{os.getpid()}"}


def _result_of(future, spec: dict, key: str) -> dict:
    """The record of a finished future: its run's, or a failure (a worker lost too often, a run
    cancelled) with the reason."""
    try:
        outcome = future.result()
    except Exception as exc:  # noqa: BLE001 - Dask's KilledWorker and the like: recorded
        outcome = {"status": "failed", "error": f"{type(exc).__name__}: {exc}", "result": None,
                   "run_s": 0.0, "started": None, "finished": time.time(), "worker": None}
    return {"key": key, "spec": spec, **outcome}


def overheads(records: list) -> list:
    """Per run, the time [s] its worker spent on anything but runs before it started (scheduling,
    transfer; the gap since that worker's previous run ended) plus the writing of its record."""
    out = []
    by_worker: dict = {}
    for r in sorted((r for r in records if r.get("started") is not None), key=lambda r: r["started"]):
        previous = by_worker.get(r["worker"])
        if previous is not None:
            out.append(max(0.0, r["started"] - previous) + r.get("written_s", 0.0))
        by_worker[r["worker"]] = r["finished"]
    return out


def map_runs(function: str, specs: list, *, workers: Optional[int] = None,
             scheduler: Optional[str] = None) -> list:
    """The results of ``function`` on each of ``specs``, in their order, run as a campaign in a
    scratch folder: what a script that wants the results and not a campaign's folder calls (the
    bench scripts). RuntimeError naming every run that failed: a failed run is not a result."""
    import tempfile
    with tempfile.TemporaryDirectory(prefix="soft-arm-runs-") as folder:
        outcome = run_campaign(folder, function, specs, workers=workers, scheduler=scheduler)
    if outcome.interrupted:
        raise KeyboardInterrupt
    by_key = {r["key"]: r for r in outcome.records}
    failed = [by_key[key_of(spec)] for spec in specs if by_key[key_of(spec)]["status"] != "ok"]
    if failed:
        raise RuntimeError(f"{len(failed)} of {len(specs)} runs failed:\n"
                           + "\n".join(f"{canonical(r['spec'])}: {r['error']}" for r in failed))
    return [by_key[key_of(spec)]["result"] for spec in specs]
