"""Issue 29 item 5: a Dask cluster that loses its workers says so. Work that waits with no worker
in the cluster gives up after ``--worker-timeout`` seconds with one line saying what to do (it
used to wait for good, silently); the banner's worker count is the cluster's, 0 included. And a
malformed ``--scheduler`` address is one line, with no ignored-exception traceback after it."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers.runner import cluster

distributed = pytest.importorskip("distributed")


@pytest.fixture
def scheduler_only():
    """A scheduler in this process with no worker at all (starts in well under a second); what
    it leaves in this process is put back after it, as ``open_executor`` does."""
    traces = cluster._Traces()
    with distributed.LocalCluster(
        n_workers=0, processes=False, dashboard_address=None, silence_logs=50
    ) as started:
        client = distributed.Client(started, set_as_default=False)
        yield started, client
        client.close()
    traces.restore()


def _slowly(item: int) -> int:
    time.sleep(0.3)
    return item * 2


def test_work_on_a_cluster_without_workers_gives_up_after_the_worker_timeout(scheduler_only):
    local, client = scheduler_only
    executor = cluster.DaskExecutor(client, worker_timeout_s=1.5)
    assert executor.workers == 0
    assert executor.description.endswith("(0 workers)")  # was "(1 workers)"
    started = time.monotonic()
    with pytest.raises(cluster.ClusterError) as error:
        list(executor.map(_slowly, [1, 2, 3], ["a", "b", "c"]))
    assert 1.5 <= time.monotonic() - started < patience(10)
    message = str(error.value)
    assert "\n" not in message
    assert f"the Dask cluster at {local.scheduler_address} has had no worker for 1.5 s" in message
    assert "with 3 of 3 tasks left" in message and "--worker-timeout SECONDS" in message


def test_a_cluster_that_loses_its_last_worker_mid_run_says_so(scheduler_only):
    local, client = scheduler_only
    local.scale(1)
    client.wait_for_workers(1, timeout=patience(30))
    executor = cluster.DaskExecutor(client, worker_timeout_s=1.0)
    assert executor.description.endswith("(1 worker)")
    results = executor.map(_slowly, list(range(8)), [f"item-{i}" for i in range(8)])
    first = next(results)
    assert first[1] == 2 * first[0]
    local.scale(0)  # every worker gone, work left
    with pytest.raises(cluster.ClusterError, match=r"has had no worker for 1 s, with \d of 8"):
        list(results)


def test_the_worker_timeout_is_an_option_and_bounded():
    from factorq_trainers.distributed import sweep

    args = sweep.build_parser().parse_args(["--grid", "eta=0.1", "--worker-timeout", "600"])
    assert cluster.where_from_args(args).worker_timeout_s == 600.0
    for bad in (0, -1, 1e9):
        with pytest.raises(cluster.ClusterError, match=r"--worker-timeout=.* is out of range"):
            cluster.Where(worker_timeout_s=bad)


def test_a_malformed_scheduler_address_is_one_line_without_an_ignored_traceback(tmp_path):
    """In a child process: the traceback came from a half-made Client collected at exit."""
    address = "evil://x"
    done = subprocess.run(
        [sys.executable, "-m", "factorq_trainers.cli", "sweep", "--grid", "eta=0.1"]
        + ["--scheduler", address, "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=patience(60),
        cwd=tmp_path,
    )
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith(
        f"factorq sweep: error: --scheduler={address!r} is not a Dask scheduler address like "
        "tcp://host:8786 (unknown address scheme 'evil'"
    )
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("address", ["tcp://localhost:abc", "tcp://"])
def test_a_malformed_scheduler_address_is_refused_before_a_client_is_made(address, monkeypatch):
    class NoClient:
        def __init__(self, *args, **kwargs):
            pytest.fail("a Client was made for a malformed address")

    monkeypatch.setattr(distributed, "Client", NoClient)
    with pytest.raises(cluster.ClusterError, match="is not a Dask scheduler address like"):
        cluster.open_executor(cluster.Where(scheduler=address, connect_timeout_s=1))


def test_an_address_only_the_client_refuses_leaves_no_client_to_close(recwarn):
    import gc

    started = time.monotonic()
    with pytest.raises(cluster.ClusterError, match="'inproc://' is not a Dask scheduler address"):
        cluster.open_executor(cluster.Where(scheduler="inproc://", connect_timeout_s=1))
    gc.collect()  # the half-made Client's __del__: nothing to close (was 20 s, then a traceback)
    assert time.monotonic() - started < patience(10)
