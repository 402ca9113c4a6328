"""Hardening, round three (issue 41, item 3): whatever listens at ``--scheduler`` is proven a Dask
scheduler within ``--connect-timeout`` before a Client trusts it. Loopback only, a handful of
connections, each bounded by its timeout (a regression fails the test instead of hanging it:
the command runs in a child process with a generous timeout)."""

from __future__ import annotations

import socket
import struct
import subprocess
import sys
import threading
import time

import pytest

from factorq_trainers.runner import cluster

distributed = pytest.importorskip("distributed")


@pytest.fixture
def silent_peer():
    """A listening socket that never speaks (as an HTTP server waits for a request): the kernel
    completes the connection from its backlog."""
    with socket.create_server(("127.0.0.1", 0), backlog=8) as server:
        yield f"tcp://127.0.0.1:{server.getsockname()[1]}"


@pytest.fixture
def speaking_peer():
    """``peer(reply)``: a one-connection server in a thread that sends ``reply`` on accept."""
    servers = []

    def peer(reply: bytes) -> str:
        server = socket.create_server(("127.0.0.1", 0))
        server.settimeout(30)

        def answer():
            try:
                connection, _ = server.accept()
            except OSError:
                return
            with connection:
                connection.sendall(reply)
                time.sleep(0.2)

        thread = threading.Thread(target=answer, daemon=True)
        thread.start()
        servers.append((server, thread))
        return f"tcp://127.0.0.1:{server.getsockname()[1]}"

    yield peer
    for server, thread in servers:
        server.close()
        thread.join(timeout=60)


def test_a_peer_that_never_speaks_is_refused_within_the_timeout_by_the_command(
    silent_peer, tmp_path
):
    """End to end: ``factorq sweep --scheduler`` at a silent peer (it used to wait for good)."""
    command = [sys.executable, "-m", "factorq_trainers.cli", "sweep", "--grid", "eta=0.1"]
    command += ["--scheduler", silent_peer, "--connect-timeout", "2", "--out", str(tmp_path / "o")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode != 0
    assert done.stderr.count("\n") == 1, done.stderr
    assert f"{silent_peer} is not a Dask scheduler: it did not answer as one within 2 s" in (
        done.stderr
    )


@pytest.mark.parametrize(
    ("reply", "expected"),
    [
        (b"HTTP/1.1 400 Bad Request\r\n\r\n", "its first message announces"),  # 3 EiB as a length
        (struct.pack("Q", 2**40), "its first message announces 1099511627776 bytes"),
        (struct.pack("Q", 16) + b"\x01" * 16, "its first message is not Dask's"),
        (struct.pack("Q", 100) + b"short", "its first message is not Dask's"),  # then closes
    ],
)
def test_a_peer_that_speaks_another_protocol_is_refused_in_one_line(speaking_peer, reply, expected):
    address = speaking_peer(reply)
    with pytest.raises(cluster.ClusterError, match=expected) as error:
        cluster.probe_scheduler(address, 20)
    assert "\n" not in str(error.value) and f"{address} is not a Dask scheduler" in str(error.value)


def test_a_port_that_refuses_is_retried_briefly_not_for_the_whole_timeout(monkeypatch):
    monkeypatch.setattr(cluster, "REFUSED_RETRY_S", 1.0)  # its 10 s, shortened: the same rule
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]  # closed below: a port that refuses at once
    started = time.monotonic()
    with pytest.raises(cluster.ClusterError, match=r"refused the connection \d+ times in") as got:
        cluster.probe_scheduler(f"tcp://127.0.0.1:{port}", 3600)
    assert time.monotonic() - started < 3600 / 4  # about REFUSED_RETRY_S, not an hour
    tries = int(str(got.value).split("refused the connection ")[1].split(" times")[0])
    assert tries >= 2  # retried (a scheduler still starting), not given up at the first refusal


def test_a_real_scheduler_passes_the_probe():
    traces = cluster._Traces()  # what the in-process scheduler leaves here, put back after it
    with distributed.LocalCluster(
        n_workers=0, processes=False, dashboard_address=":0", silence_logs=50
    ) as local:
        cluster.probe_scheduler(local.scheduler_address, 60)
        executor = cluster.open_executor(
            cluster.Where(scheduler=local.scheduler_address, connect_timeout_s=60)
        )
        executor.close()
    traces.restore()
