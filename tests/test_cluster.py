"""Units and sweeps on a real 2-worker Dask ``LocalCluster``: the same numbers as one process, bit
for bit, also when a worker is killed (SIGKILL) in the middle of a unit."""

from __future__ import annotations

import functools
import json
import os
import signal
import threading
import time
from dataclasses import replace

import pytest
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers import cli
from factorq_trainers.commands.paper import command as paper
from factorq_trainers.compiled import fast
from factorq_trainers.distributed import sweep, sweep_spec
from factorq_trainers.runner import cluster, frame
from factorq_trainers.runner import results as result_files

distributed = pytest.importorskip("distributed")
pytestmark = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
SMALL = {"seeds": 7, "runs": 2, "episodes": 6, "size": 6, "obstacles": 4}


@pytest.fixture(scope="module")
def local_cluster():
    """One 2-worker cluster for the module (processes, one thread each): it starts in seconds.
    What it leaves in this process (its nannies' environment variables, its scheduler's log
    handler) is put back after it, as ``open_executor`` does."""
    traces = cluster._Traces()
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=50,
    ) as started:
        yield started
    traces.restore()


@pytest.fixture
def executor(local_cluster):
    client = distributed.Client(local_cluster.scheduler_address, set_as_default=False)
    client.wait_for_workers(2, timeout=patience(60))
    running = cluster.DaskExecutor(client)  # closes the client only, not the cluster
    yield running
    running.close()


def _units_lost_with_a_worker(dask_scheduler) -> list[str]:
    return [
        str(key)
        for key, start, finish, _, stimulus, _ in dask_scheduler.transition_log
        if str(key).startswith("paper-")
        and (start, finish) == ("processing", "released")
        and stimulus.startswith("handle-worker-cleanup")
    ]


def _without_timing(results: dict) -> str:
    return result_files.dumps({**results, "timing": None})


def test_paper_units_on_two_workers_equal_one_process_bit_for_bit(executor, tmp_path):
    config = paper.PaperConfig(**SMALL, shard_seeds=2, threads=2, out=str(tmp_path / "cluster"))
    expected = paper.run(replace(config, shard_seeds=SMALL["seeds"]))  # one unit per algorithm
    units = paper.units(config)  # 2 algorithms x 4 shards: 2, 2, 2, 1 seeds
    task = functools.partial(frame.run_unit_task, paper.__name__, config)
    names = [f"paper-{unit['id']}" for unit in units]
    remote = dict(executor.map(task, units, names))
    assert executor.description.endswith("(2 workers)") and len(remote) == len(units) == 8
    outcomes = [remote[index] for index in range(len(units))]
    gathered = frame.envelope(paper, config, paper.summarise(config, outcomes), wall_s=0.0)
    for results in (gathered, expected):
        results["config"].pop("shard_seeds")
    assert _without_timing(gathered) == _without_timing(expected)
    for unit, outcome in zip(units, outcomes, strict=True):  # each the unit's alone, here
        alone = frame.unit_result(paper, config, unit, paper.run_unit(config, unit))
        assert result_files.dumps(outcome) == result_files.dumps(alone)


def test_a_sweep_on_the_cluster_equals_the_sweep_in_process(executor, tmp_path):
    spec = sweep_spec.SweepSpec(
        base=(("runs", 1), ("episodes", 5), ("size", 5), ("shard_seeds", 2)),
        grid=(("obstacles", (2, 4)), ("epsilon", (0.01, 0.05))),
        seeds=3,
        out=str(tmp_path / "cluster"),
    )
    on_cluster = sweep.run_sweep(spec, executor)
    in_process = sweep.run_sweep(replace(spec, out=str(tmp_path / "here")), cluster.InProcess())
    strip = [
        {**row, "config": {**row["config"], "out": None}} for row in on_cluster["configurations"]
    ]
    local = [
        {**row, "config": {**row["config"], "out": None}} for row in in_process["configurations"]
    ]
    assert strip == local


def test_factorq_paper_joins_a_running_scheduler(local_cluster, tmp_path, capsys):
    options = ["--seeds", "4", "--runs", "1", "--episodes", "3", "--size", "5"]
    assert cli.main(["paper", *options, "--out", str(tmp_path / "plain")]) == 0
    address = local_cluster.scheduler_address
    argv = ["paper", *options, "--scheduler", address, "--shard-seeds", "3"]
    assert cli.main([*argv, "--out", str(tmp_path / "joined")]) == 0
    plain = json.loads((tmp_path / "plain" / "results.json").read_text())
    joined = json.loads((tmp_path / "joined" / "results.json").read_text())
    assert joined["timing"]["where"].startswith(f"Dask scheduler {address}")
    assert joined["timing"]["units"] == 4  # 2 algorithms x seeds [0, 3) and [3, 4)
    for results in (plain, joined):
        results.pop("timing")
        results["config"].pop("out")
        results["config"].pop("shard_seeds")
    assert joined == plain


def test_an_unreachable_scheduler_is_one_line_exit_2_within_the_timeout(tmp_path, capsys):
    out = tmp_path / "sweep"
    started = time.monotonic()
    argv = ["sweep", "--grid", "eta=0.1,0.2", "--scheduler", "tcp://127.0.0.1:9"]
    assert cli.main([*argv, "--connect-timeout", "1", "--out", str(out)]) == 2
    assert time.monotonic() - started < patience(10)
    error = capsys.readouterr().err
    assert error.count("\n") == 1
    # nothing listens there: refused at once, retried briefly (issue 41), one line
    assert "scheduler tcp://127.0.0.1:9 refused the connection" in error
    assert not out.exists()


@pytest.mark.module_threads  # the module's cluster restarts the killed worker: its watchers
def test_a_worker_killed_mid_unit_loses_only_that_unit_and_the_numbers_stay(
    local_cluster, executor, tmp_path, capsys
):
    # Units of a second or two each on one thread (an algorithm's 60 seeds), so the kill lands
    # inside one.
    out = tmp_path / "killed"
    options = ["--seeds", "60", "--shard-seeds", "60", "--threads", "1"]
    argv = ["paper", *options, "--scheduler", local_cluster.scheduler_address, "--out", str(out)]
    client = executor.client
    pids = client.run(os.getpid)  # worker address -> process id
    outcome: dict = {}

    def run() -> None:
        try:
            outcome["code"] = cli.main(argv)
        except BaseException as error:  # reported by the assertion below
            outcome["error"] = error

    runner = threading.Thread(target=run)
    runner.start()
    killed = None
    deadline = time.monotonic() + patience(60)
    while killed is None and time.monotonic() < deadline and runner.is_alive():
        for address, keys in client.processing().items():
            if any(str(key).startswith("paper-") for key in keys) and address in pids:
                time.sleep(0.3)  # well inside the unit's seconds of work
                os.kill(pids[address], signal.SIGKILL)
                killed = address
                break
        time.sleep(0.02)
    runner.join(timeout=patience(120))
    assert killed is not None, "no unit was seen running: nothing was killed"
    assert "error" not in outcome, outcome.get("error")
    assert outcome["code"] == 0, capsys.readouterr().err
    assert pids[killed] not in client.run(os.getpid).values()  # that process is gone
    # The scheduler's log: exactly one unit was lost with its worker (processing -> released on
    # the worker's clean-up) and computed again; the other ran once.
    lost = client.run_on_scheduler(_units_lost_with_a_worker)
    assert len(lost) == 1, lost
    results = json.loads((out / "results.json").read_text())
    assert results["timing"]["units"] == 2 and results["timing"]["units_resumed"] == 0
    expected = paper.run(paper.PaperConfig(seeds=60, shard_seeds=60, threads=1, out=str(out)))
    assert _without_timing(results) == _without_timing(json.loads(result_files.dumps(expected)))
    assert not (out / "units").exists()  # the kept units go once the results are written


def test_factorq_compare_on_the_cluster_repeats_every_method_in_process(
    local_cluster, tmp_path, capsys
):
    """One unit (a method's batch) per task on the runner's frame: every method, DQN included,
    repeats its in-process numbers."""
    options = ["--seeds", "2", "--steps", "100", "--size", "4", "--obstacles", "2"]
    options += ["--regimes", "static,dynamic", "--threads", "1"]
    assert cli.main(["compare", *options, "--out", str(tmp_path / "here")]) == 0
    address = local_cluster.scheduler_address
    argv = ["compare", *options, "--scheduler", address, "--out", str(tmp_path / "cluster")]
    assert cli.main(argv) == 0
    expected = json.loads((tmp_path / "here" / "comparison.json").read_text())
    results = json.loads((tmp_path / "cluster" / "comparison.json").read_text())
    assert address in results["timing"]["where"] and results["timing"]["units"] == 4
    for summary in (expected, results):
        summary.pop("timing")
        summary["config"].pop("out")
        for worlds in summary["results"].values():
            for cell in worlds.values():
                cell.pop("wall_s")
    assert results == expected


def test_factorq_sweep_on_a_running_scheduler_writes_what_it_writes_in_process(
    local_cluster, tmp_path, capsys
):
    argv = ["sweep", "--grid", "obstacles=2,3", "--set", "runs=1", "--set", "episodes=3"]
    argv += ["--set", "size=5", "--set", "shard_seeds=2", "--seeds", "3"]
    address = local_cluster.scheduler_address
    assert cli.main([*argv, "--scheduler", address, "--out", str(tmp_path / "joined")]) == 0
    assert cli.main([*argv, "--out", str(tmp_path / "here")]) == 0
    joined = json.loads((tmp_path / "joined" / "sweep.json").read_text())
    here = json.loads((tmp_path / "here" / "sweep.json").read_text())
    assert joined["timing"]["where"].startswith(f"Dask scheduler {address}")
    for sweep_json in (joined, here):
        for row in sweep_json["configurations"]:
            row["config"].pop("out")
    assert joined["configurations"] == here["configurations"]
    assert (tmp_path / "joined" / "sweep-obstacles.png").stat().st_size > 10_000


def test_a_compare_sweep_on_the_cluster_writes_what_it_writes_in_process(
    local_cluster, tmp_path, capsys
):
    argv = ["sweep", "--command", "compare", "--grid", "obstacles=1,2", "--seeds", "2"]
    argv += ["--set", "steps=100", "--set", "size=4", "--set", "regimes=static,dynamic"]
    argv += ["--set", "methods=factor-q,q-learning"]
    address = ["--scheduler", local_cluster.scheduler_address]  # what --cluster local:2 starts
    assert cli.main([*argv, *address, "--out", str(tmp_path / "cluster")]) == 0
    assert cli.main([*argv, "--out", str(tmp_path / "here")]) == 0
    on_cluster = json.loads((tmp_path / "cluster" / "sweep.json").read_text())
    here = json.loads((tmp_path / "here" / "sweep.json").read_text())
    assert on_cluster["timing"]["where"].startswith("Dask scheduler")
    for sweep_json in (on_cluster, here):
        for row in sweep_json["configurations"]:
            row["config"].pop("out")
    assert on_cluster["configurations"] == here["configurations"]
    for row in here["configurations"]:  # and each configuration's file is factorq compare's
        stored = json.loads((tmp_path / "here" / row["results_file"]).read_text())
        cluster_file = tmp_path / "cluster" / row["results_file"]
        remote = json.loads(cluster_file.read_text())
        for results in (stored, remote):
            results.pop("timing")
            results.pop("content_sha256")  # of the timing too: checked when the file is reused
            results["config"].pop("out")
            for worlds in results["results"].values():
                for cell in worlds.values():
                    cell.pop("wall_s")
        assert remote == stored
